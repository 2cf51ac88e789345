"""Each agent loss equals the same quantity recomputed by hand in NumPy on a tiny network.

The random draws (uniform CQL actions, the Gaussian noise of policy samples, the critic
subset) are re-drawn here from the same keys with the agents' documented key splits; all
the arithmetic after that is NumPy. Tolerance: 1e-4 relative + 1e-4 absolute (float32).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from botorl.agents.cql import CQLAgent, CQLConfig
from botorl.agents.iql import IQLAgent, IQLConfig
from botorl.agents.sac import SACAgent, SACConfig
from botorl.networks import sample_tanh_gaussian, tanh_gaussian_log_prob

O, A, B = 3, 2, 5
TOL = dict(rtol=1e-4, atol=1e-4)


# ---------------------------------------------------------------- numpy forward passes
def np_mlp(p, x, n_layers, layer_norm, activate_final=True):
    for i in range(n_layers):
        d = p[f"Dense_{i}"]
        x = x @ np.asarray(d["kernel"]) + np.asarray(d["bias"])
        if i + 1 < n_layers or activate_final:
            if layer_norm:
                ln = p[f"LayerNorm_{i}"]
                mu = x.mean(-1, keepdims=True)
                var = x.var(-1, keepdims=True)
                x = (x - mu) / np.sqrt(var + 1e-6) * np.asarray(ln["scale"]) + np.asarray(ln["bias"])
            x = np.maximum(x, 0.0)
    return x


def np_critic(params, obs, act, n_layers, layer_norm):
    """(N, B) from the ensemble params (leading axis N)."""
    members = params["members"]
    n = np.asarray(members["Dense_0"]["kernel"]).shape[0]
    out = []
    for i in range(n):
        p = jax.tree_util.tree_map(lambda x: np.asarray(x)[i], members)
        h = np_mlp(p["MLP_0"], np.concatenate([obs, act], -1), n_layers, layer_norm)
        out.append((h @ p["Dense_0"]["kernel"] + p["Dense_0"]["bias"])[..., 0])
    return np.stack(out)


def np_actor(params, obs, n_layers, layer_norm, lo, hi):
    h = np_mlp(params["MLP_0"], obs, n_layers, layer_norm)
    mean = h @ np.asarray(params["mean"]["kernel"]) + np.asarray(params["mean"]["bias"])
    if "log_std" in params and isinstance(params["log_std"], dict):
        log_std = h @ np.asarray(params["log_std"]["kernel"]) + np.asarray(params["log_std"]["bias"])
    else:
        log_std = np.broadcast_to(np.asarray(params["log_std"]), mean.shape)
    return mean, np.clip(log_std, lo, hi)


def np_tanh_sample(mean, log_std, eps):
    u = mean + np.exp(log_std) * eps
    a = np.tanh(u)
    normal = -0.5 * eps**2 - log_std - 0.5 * np.log(2 * np.pi)
    logp = normal.sum(-1) - np.log(1 - np.tanh(u) ** 2).sum(-1)
    return a, logp


def np_logsumexp(x, axis):
    m = x.max(axis, keepdims=True)
    return (m + np.log(np.exp(x - m).sum(axis, keepdims=True))).squeeze(axis)


def make_batch(seed, b=B, mc=None):
    r = np.random.default_rng(seed)
    return {
        "observations": r.normal(size=(b, O)).astype(np.float32),
        "actions": r.uniform(-0.9, 0.9, (b, A)).astype(np.float32),
        "rewards": r.normal(size=b).astype(np.float32),
        "next_observations": r.normal(size=(b, O)).astype(np.float32),
        "dones": (r.uniform(size=b) < 0.3).astype(np.float32),
        "mc_returns": (np.zeros(b) if mc is None else mc).astype(np.float32),
    }


TINY = dict(actor_hidden_dims=(8, 8), critic_hidden_dims=(8, 8), num_critics=4)


def _jnp_batch(b):
    return {k: jnp.asarray(v) for k, v in b.items()}


# ---------------------------------------------------------------- tests
def test_tanh_gaussian_log_prob_matches_numpy():
    r = np.random.default_rng(0)
    mean = r.normal(size=(4, A)).astype(np.float32)
    log_std = r.normal(scale=0.5, size=(4, A)).astype(np.float32)
    key = jax.random.PRNGKey(3)
    acts, logp = sample_tanh_gaussian(key, jnp.asarray(mean), jnp.asarray(log_std))
    eps = np.asarray(jax.random.normal(key, (4, A)))
    a_np, logp_np = np_tanh_sample(mean, log_std, eps)
    np.testing.assert_allclose(acts, a_np, **TOL)
    np.testing.assert_allclose(logp, logp_np, **TOL)
    # The log-prob of given actions (atanh path) agrees with the sampling path.
    np.testing.assert_allclose(tanh_gaussian_log_prob(jnp.asarray(mean), jnp.asarray(log_std), acts), logp, rtol=1e-3, atol=1e-3)


@pytest.mark.parametrize("replace", [True, False])
def test_subset_min_target(replace):
    cfg = SACConfig(**TINY, num_min_critics=2, subsample_replace=replace, backup_entropy=True)
    agent = SACAgent.create(cfg, O, A, seed=1)
    # Distinct target params so the subset matters.
    agent = agent.replace(target_critic_params=jax.tree_util.tree_map(lambda x: x * 1.3 + 0.01, agent.critic.params))
    batch = make_batch(0)
    key = jax.random.PRNGKey(7)
    target, _ = agent.target_values(_jnp_batch(batch), key)

    k_act, k_sub = jax.random.split(key)
    if replace:
        idx = np.asarray(jax.random.randint(k_sub, (2,), 0, 4))
    else:
        idx = np.asarray(jax.random.permutation(k_sub, 4)[:2])
    eps = np.asarray(jax.random.normal(k_act, (B, A)))
    mean, log_std = np_actor(agent.actor.params, batch["next_observations"], 2, True, -20, 2)
    a, logp = np_tanh_sample(mean, log_std, eps)
    q = np_critic(agent.target_critic_params, batch["next_observations"], a, 2, True)[idx].min(0)
    temp = 1.0
    want = batch["rewards"] + 0.99 * (1 - batch["dones"]) * (q - temp * logp)
    np.testing.assert_allclose(target, want, **TOL)


def test_two_critic_baseline_target_is_min_of_both_and_penalises_both():
    # Cal-QL / CQL as WSRL runs them as baselines (resolved presets): 2 critics, no subset. The
    # target must be the min of both target critics for every key (a pair drawn with
    # replacement would be one critic in half of the draws) and the penalty covers both.
    from botorl.configs.presets import make_preset
    from botorl.configs.resolve import resolve

    base = resolve(make_preset("pointmaze-umaze", "quick", "calql")).offline.cql
    from dataclasses import replace as dc_replace

    cfg = dc_replace(base, actor_hidden_dims=(8, 8), critic_hidden_dims=(8, 8), actor_layer_norm=False,
                     critic_layer_norm=False, max_target_backup=False, backup_entropy=False)
    agent = CQLAgent.create(cfg, O, A, seed=2)
    agent = agent.replace(target_critic_params=jax.tree_util.tree_map(lambda x: x * 1.3 + 0.01, agent.critic.params))
    batch = make_batch(4)
    mean, log_std = np_actor(agent.actor.params, batch["next_observations"], 2, False, cfg.log_std_min, cfg.log_std_max)
    for k in range(8):
        key = jax.random.PRNGKey(k)
        assert agent.penalty_members(key) is None
        target, _ = agent.target_values(_jnp_batch(batch), key)
        k_act, _ = jax.random.split(key)
        a, _ = np_tanh_sample(mean, log_std, np.asarray(jax.random.normal(k_act, (B, A))))
        q = np_critic(agent.target_critic_params, batch["next_observations"], a, 2, False).min(0)
        np.testing.assert_allclose(target, batch["rewards"] + 0.99 * (1 - batch["dones"]) * q, **TOL)


def test_max_target_backup():
    n = 3
    cfg = SACConfig(**TINY, num_min_critics=3, max_target_backup=True, num_backup_actions=n, backup_entropy=True)
    agent = SACAgent.create(cfg, O, A, seed=2)
    batch = make_batch(1)
    key = jax.random.PRNGKey(11)
    target, _ = agent.target_values(_jnp_batch(batch), key)

    k_act, k_sub = jax.random.split(key)
    idx = np.asarray(jax.random.randint(k_sub, (3,), 0, 4))
    eps = np.asarray(jax.random.normal(k_act, (B, n, A)))
    mean, log_std = np_actor(agent.actor.params, batch["next_observations"], 2, True, -20, 2)
    a, logp = np_tanh_sample(mean[:, None], log_std[:, None], eps)  # (B, n, A), (B, n)
    obs_rep = np.repeat(batch["next_observations"], n, axis=0)
    q = np_critic(agent.target_critic_params, obs_rep, a.reshape(B * n, A), 2, True)[idx].min(0).reshape(B, n)
    best = q.argmax(1)
    # min over the subset, max over the n actions; the entropy term of that argmax action.
    v = q[np.arange(B), best] - 1.0 * logp[np.arange(B), best]
    want = batch["rewards"] + 0.99 * (1 - batch["dones"]) * v
    np.testing.assert_allclose(target, want, **TOL)


def test_temperature_loss_and_direction():
    agent = SACAgent.create(SACConfig(**TINY, init_temp=0.5), O, A, seed=0)
    assert agent.config.target_entropy == -A
    loss, info = agent.temp_loss(agent.temp.params, jnp.asarray(-4.0))
    np.testing.assert_allclose(loss, 0.5 * (-4.0 - (-A)), **TOL)
    # Entropy below target -> gradient step raises the temperature.
    agent2, _ = agent.temp_step(jnp.asarray(-4.0))
    assert float(agent2.temperature()) > 0.5
    agent3, _ = agent.temp_step(jnp.asarray(0.0))
    assert float(agent3.temperature()) < 0.5


@pytest.mark.parametrize("calql", [False, True])
def test_cql_penalty_with_importance_sampling(calql):
    n = 3
    cfg = CQLConfig(**TINY, cql_n_actions=n, calql=calql, cql_lagrange=True, cql_weight=2.0, cql_target_action_gap=0.5)
    agent = CQLAgent.create(cfg, O, A, seed=3)
    mc = np.array([-5.0, 5.0, 0.0, 10.0, -1.0])  # some rows bound, some not
    batch = make_batch(2, mc=mc)
    key = jax.random.PRNGKey(5)
    diff, q_data, info = agent.cql_penalty(agent.critic.params, _jnp_batch(batch), key)

    k_unif, k_cur, k_next = jax.random.split(key, 3)
    unif = np.asarray(jax.random.uniform(k_unif, (B, n, A), minval=-1.0, maxval=1.0))
    m_s, ls_s = np_actor(agent.actor.params, batch["observations"], 2, True, -20, 2)
    m_n, ls_n = np_actor(agent.actor.params, batch["next_observations"], 2, True, -20, 2)
    a_cur, lp_cur = np_tanh_sample(m_s[:, None], ls_s[:, None], np.asarray(jax.random.normal(k_cur, (B, n, A))))
    a_nxt, lp_nxt = np_tanh_sample(m_n[:, None], ls_n[:, None], np.asarray(jax.random.normal(k_next, (B, n, A))))
    obs = batch["observations"]
    p = agent.critic.params

    def q_at(acts):  # (B, n, A) scored at s -> (N, B, n)
        return np_critic(p, np.repeat(obs, n, 0), acts.reshape(B * n, A), 2, True).reshape(-1, B, n)

    q_u, q_c, q_n = q_at(unif), q_at(a_cur), q_at(a_nxt)
    q_d = np_critic(p, obs, batch["actions"], 2, True)
    if calql:  # Cal-QL: policy-sample Q lower-bounded by the MC return; uniform ones not
        q_c = np.maximum(q_c, mc[None, :, None])
        q_n = np.maximum(q_n, mc[None, :, None])
    cat = np.concatenate([q_u - A * np.log(0.5), q_n - lp_nxt[None], q_c - lp_cur[None]], -1)
    want_diff = (np_logsumexp(cat, -1) - q_d).mean(-1)
    np.testing.assert_allclose(q_data, q_d, **TOL)
    np.testing.assert_allclose(diff, want_diff, **TOL)

    # Whole critic loss with the Lagrange weight alpha' = e (log alpha' starts at 1), WSRL's
    # form: alpha' (diff - gap) with no cql_weight factor (the config's 2.0 must not enter).
    target = jnp.asarray(make_batch(9)["rewards"])
    loss, _ = agent.critic_loss(p, _jnp_batch(batch), target, key)
    bellman = ((q_d - np.asarray(target)[None]) ** 2).mean(-1)
    want_loss = np.mean(bellman + math.e * (want_diff - 0.5))
    np.testing.assert_allclose(loss, want_loss, **TOL)
    # Multiplier loss: -mean(alpha' (diff - gap)); alpha' rises while diff > gap.
    l_loss = agent.lagrange_loss(agent.lagrange.params, jnp.asarray(want_diff))
    np.testing.assert_allclose(l_loss, -np.mean(math.e * (want_diff - 0.5)), **TOL)


@pytest.mark.parametrize("calql,lagrange", [(False, False), (True, True)])
def test_cql_chunked_gradient_equals_whole_batch_gradient(calql, lagrange):
    # critic_grads sums the gradients of chunks of states (CPU cache locality); it must be
    # the gradient of critic_loss on the whole batch, with the same info.
    n = 2  # 3n + 1 = 7 rows per state
    base = dict(TINY, cql_n_actions=n, calql=calql, cql_lagrange=lagrange, cql_weight=2.0, cql_target_action_gap=0.5)
    whole = CQLAgent.create(CQLConfig(**base, chunk_rows=0), O, A, seed=6)
    chunked = CQLAgent.create(CQLConfig(**base, chunk_rows=14), O, A, seed=6)  # 2 states per chunk
    bsz = 6
    batch = _jnp_batch(make_batch(7, b=bsz, mc=np.linspace(-3.0, 3.0, bsz)))
    assert whole.chunk_states(bsz) == bsz and chunked.chunk_states(bsz) == 2
    target = jnp.asarray(np.linspace(-1.0, 1.0, bsz), jnp.float32)
    key = jax.random.PRNGKey(2)
    p = whole.critic.params
    (_, info), g_auto = jax.value_and_grad(whole.critic_loss, has_aux=True)(p, batch, target, key)
    g_whole, info_whole = whole.critic_grads(p, batch, target, key)
    g_chunk, info_chunk = chunked.critic_grads(p, batch, target, key)
    for g in (g_whole, g_chunk):
        jax.tree_util.tree_map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6), g, g_auto)
    assert max(float(jnp.abs(x).max()) for x in jax.tree_util.tree_leaves(g_auto)) > 1e-3  # not trivially zero
    for key_name, value in info.items():
        np.testing.assert_allclose(info_chunk[key_name], value, rtol=1e-5, atol=1e-6, err_msg=key_name)
        np.testing.assert_allclose(info_whole[key_name], value, rtol=1e-5, atol=1e-6, err_msg=key_name)
    # States per chunk: the largest divisor of the batch whose rows fit the chunk.
    big = CQLAgent.create(CQLConfig(**dict(TINY, cql_n_actions=10), chunk_rows=256), O, A, seed=0)
    assert big.chunk_states(256) == 8 and big.chunk_states(7) == 7 and big.chunk_states(250) == 5


def test_sac_actor_chunked_gradient_equals_whole_batch_gradient():
    from botorl.agents.common import chunk_size, summed_value_and_grad

    agent = SACAgent.create(SACConfig(**TINY, chunk_rows=2), O, A, seed=8)
    bsz = 6
    batch = _jnp_batch(make_batch(11, b=bsz))
    key = jax.random.PRNGKey(4)
    (loss, info), g_whole = jax.value_and_grad(agent.actor_loss, has_aux=True)(agent.actor.params, batch, key)
    per = chunk_size(bsz, 1, agent.config.chunk_rows)
    assert per == 2
    (loss_c, neg_logp), g_chunk = summed_value_and_grad(
        lambda p, r: agent._actor_loss_sum(p, r, bsz), agent.actor.params, agent._actor_rows(batch, key), per)
    np.testing.assert_allclose(loss_c, loss, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(neg_logp / bsz, info["entropy"], rtol=1e-5, atol=1e-6)
    jax.tree_util.tree_map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6), g_chunk, g_whole)
    assert max(float(jnp.abs(x).max()) for x in jax.tree_util.tree_leaves(g_whole)) > 1e-3
    # actor_step reports the same loss and entropy as actor_loss
    _, step_info = agent.actor_step(batch, key)
    np.testing.assert_allclose(step_info["actor_loss"], loss, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(step_info["entropy"], info["entropy"], rtol=1e-5, atol=1e-6)
    # chunk sizes: no chunking for 0, or when the rows fit
    assert chunk_size(1024, 1, 256) == 256 and chunk_size(1024, 1, 0) == 1024 and chunk_size(200, 1, 256) == 200
    # unset: sized to ~256k activation floats per layer, at least 256 rows (CPU; tests run there)
    from botorl.agents.common import auto_chunk_rows

    assert jax.default_backend() == "cpu"
    assert [auto_chunk_rows(n * w) for n, w in ((2, 256), (10, 256), (2, 512), (2, 64))] == [512, 256, 256, 2048]
    assert chunk_size(256, 31, None, 2 * 256) == 16 and chunk_size(1024, 1, None, 10 * 256) == 256


def test_no_chunking_off_the_cpu(monkeypatch):
    # On an accelerator one big batch is faster: unset chunk_rows means one chunk there.
    from botorl.agents import common

    monkeypatch.setattr(common.jax, "default_backend", lambda: "gpu")
    assert common.auto_chunk_rows(2 * 256) == 0
    assert common.chunk_size(256, 31, None, 2 * 256) == 256 and common.chunk_size(1024, 1, None, 2560) == 1024
    assert common.chunk_size(1024, 1, 256, 2560) == 256  # an explicit size still applies


def test_cql_penalty_without_importance_sampling():
    n = 2
    cfg = CQLConfig(**TINY, cql_n_actions=n, cql_importance_sample=False, cql_temp=0.5, cql_lagrange=False)
    agent = CQLAgent.create(cfg, O, A, seed=4)
    batch = make_batch(3)
    key = jax.random.PRNGKey(1)
    diff, _, _ = agent.cql_penalty(agent.critic.params, _jnp_batch(batch), key)
    k_unif, k_cur, k_next = jax.random.split(key, 3)
    unif = np.asarray(jax.random.uniform(k_unif, (B, n, A), minval=-1.0, maxval=1.0))
    m_s, ls_s = np_actor(agent.actor.params, batch["observations"], 2, True, -20, 2)
    m_n, ls_n = np_actor(agent.actor.params, batch["next_observations"], 2, True, -20, 2)
    a_cur, _ = np_tanh_sample(m_s[:, None], ls_s[:, None], np.asarray(jax.random.normal(k_cur, (B, n, A))))
    a_nxt, _ = np_tanh_sample(m_n[:, None], ls_n[:, None], np.asarray(jax.random.normal(k_next, (B, n, A))))
    obs, p = batch["observations"], agent.critic.params
    q_at = lambda acts: np_critic(p, np.repeat(obs, n, 0), acts.reshape(B * n, A), 2, True).reshape(-1, B, n)  # noqa: E731
    q_d = np_critic(p, obs, batch["actions"], 2, True)
    cat = np.concatenate([q_at(unif), q_d[..., None], q_at(a_nxt), q_at(a_cur)], -1)
    want = (0.5 * np_logsumexp(cat / 0.5, -1) - q_d).mean(-1)
    np.testing.assert_allclose(diff, want, **TOL)


def test_iql_expectile_and_awr_losses():
    cfg = IQLConfig(actor_hidden_dims=(8, 8), critic_hidden_dims=(8, 8), value_hidden_dims=(8, 8), expectile=0.7, awr_beta=3.0)
    agent = IQLAgent.create(cfg, O, A, seed=5)
    batch = make_batch(4)
    q = np_critic(agent.target_critic_params, batch["observations"], batch["actions"], 2, False).min(0)
    # with two critics the random pair is both: IQL's twin-Q min
    q_agent = agent.target_q(_jnp_batch(batch), jax.random.PRNGKey(3))
    np.testing.assert_allclose(q_agent, q, **TOL)
    loss, _ = agent.value_loss(agent.value.params, _jnp_batch(batch), q_agent)
    vp = agent.value.params
    v = (np_mlp(vp["MLP_0"], batch["observations"], 2, False) @ np.asarray(vp["Dense_0"]["kernel"]) + np.asarray(vp["Dense_0"]["bias"]))[:, 0]
    d = q - v
    want = np.mean(np.where(d < 0, 0.3, 0.7) * d**2)
    np.testing.assert_allclose(loss, want, **TOL)

    a_loss, _ = agent.actor_loss(agent.actor.params, _jnp_batch(batch), jax.random.PRNGKey(0), q_agent)
    mean, log_std = np_actor(agent.actor.params, batch["observations"], 2, False, -5, 2)
    u = np.arctanh(batch["actions"])
    logp = (-0.5 * ((u - mean) / np.exp(log_std)) ** 2 - log_std - 0.5 * np.log(2 * np.pi)).sum(-1) - np.log(1 - batch["actions"] ** 2).sum(-1)
    w = np.minimum(np.exp(3.0 * d), 100.0)
    np.testing.assert_allclose(a_loss, -np.mean(w * logp), rtol=1e-3, atol=1e-3)


def test_iql_target_is_min_over_a_distinct_pair_of_a_larger_ensemble():
    cfg = IQLConfig(actor_hidden_dims=(8, 8), critic_hidden_dims=(8, 8), value_hidden_dims=(8, 8), num_critics=4)
    agent = IQLAgent.create(cfg, O, A, seed=6)
    batch = make_batch(4)
    per_member = np_critic(agent.target_critic_params, batch["observations"], batch["actions"], 2, False)  # (4, B)
    pairs = {(i, j): np.minimum(per_member[i], per_member[j]) for i in range(4) for j in range(i + 1, 4)}
    seen = set()
    for k in range(12):
        q = np.asarray(agent.target_q(_jnp_batch(batch), jax.random.PRNGKey(k)))
        match = [p for p, v in pairs.items() if np.allclose(q, v, rtol=1e-4, atol=1e-5)]
        assert match, "the target must be the min over two distinct members"
        seen.update(match)
    assert len(seen) >= 3, f"the pair must be drawn at random, saw only {seen}"


def test_cql_penalty_on_a_random_subset_of_members():
    # WSRL's Cal-QL with a 10-critic ensemble penalises a random pair each step: the penalty of
    # the subset must be the full ensemble's penalty at the drawn members, averaged over them
    # (WSRL's cql_loss is a mean), the Bellman term still every member's.
    from dataclasses import replace as dc_replace

    cfg = CQLConfig(**{**TINY, "num_critics": 4}, cql_n_actions=2, calql=True, cql_lagrange=False, cql_weight=2.0)
    full = CQLAgent.create(cfg, O, A, seed=3)
    sub = full.replace(config=dc_replace(cfg, cql_penalty_critics=2))
    batch = _jnp_batch(make_batch(2, mc=np.array([-5.0, 5.0, 0.0, 10.0, -1.0])))
    members = np.asarray(sub.penalty_members(jax.random.PRNGKey(7)))
    assert members.shape == (2,) and ((0 <= members) & (members < 4)).all()
    d_full, q_full, _ = full.cql_penalty(full.critic.params, batch, jax.random.PRNGKey(7))
    d_sub, q_sub, _ = sub.cql_penalty(sub.critic.params, batch, jax.random.PRNGKey(7))
    np.testing.assert_allclose(d_sub, np.asarray(d_full)[members], **TOL)
    np.testing.assert_allclose(q_sub, q_full, **TOL)
    target = jnp.asarray(make_batch(9)["rewards"])
    loss, _ = sub.critic_loss(sub.critic.params, batch, target, jax.random.PRNGKey(7))
    bellman = ((np.asarray(q_full) - np.asarray(target)[None]) ** 2).mean(-1)
    # WSRL's scale: the mean penalty over the K penalised members (not their sum over N), so the
    # weight means the same against the Bellman error whatever K / N is
    np.testing.assert_allclose(loss, bellman.mean() + 2.0 * np.asarray(d_full)[members].mean(), **TOL)
    # chunked gradient == whole-batch gradient with the subset too
    g_whole = jax.grad(lambda p: sub.critic_loss(p, batch, target, jax.random.PRNGKey(7))[0])(sub.critic.params)
    chunked = sub.replace(config=dc_replace(sub.config, chunk_rows=7))
    g_chunk, _ = chunked.critic_grads(sub.critic.params, batch, target, jax.random.PRNGKey(7))
    for a, b in zip(jax.tree_util.tree_leaves(g_whole), jax.tree_util.tree_leaves(g_chunk)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)

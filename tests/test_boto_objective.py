"""The BOTO target against a NumPy hand computation, and run_boto on Cal-QL / CQL / IQL agents."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from botorl.agents.cql import CQLAgent, CQLConfig
from botorl.agents.iql import IQLAgent, IQLConfig
from botorl.agents.sac import SACAgent, SACConfig
from botorl.boto import BOTOConfig, run_boto
from botorl.boto.objective import ObjectiveSettings, boto_update, compute_target
from botorl.data.dataset import Dataset
from botorl.errors import ConfigError

O, A = 3, 2
TINY = dict(actor_hidden_dims=(8,), critic_hidden_dims=(8,), actor_layer_norm=False, critic_layer_norm=False)


def _np_tanh_gaussian(mean, log_std, eps):
    u = mean + np.exp(log_std) * eps
    logp = np.sum(-0.5 * eps**2 - log_std - 0.5 * math.log(2 * math.pi), -1) - np.sum(np.log(1 - np.tanh(u) ** 2), -1)
    return np.tanh(u), logp


@pytest.mark.parametrize("backup_entropy", [True, False])
def test_target_matches_numpy(backup_entropy):
    agent = SACAgent.create(SACConfig(**TINY, num_critics=3, num_min_critics=3, subsample_replace=False,
                                      init_temp=0.5, discount=0.9), O, A, seed=1)
    rng = np.random.default_rng(0)
    batch = {
        "observations": rng.normal(size=(4, O)).astype(np.float32),
        "actions": rng.uniform(-0.9, 0.9, (4, A)).astype(np.float32),
        "rewards": np.array([1.0, -0.5, 0.25, 2.0], np.float32),
        "next_observations": rng.normal(size=(4, O)).astype(np.float32),
        "dones": np.array([0.0, 1.0, 0.0, 0.0], np.float32),
    }
    alpha = -0.7
    settings = ObjectiveSettings.resolve(BOTOConfig(noise="gaussian", sigma=0.3,
                                                    backup_entropy=backup_entropy), agent)
    k_noise, k_next = jax.random.PRNGKey(11), jax.random.PRNGKey(12)
    jb = {k: jnp.asarray(v) for k, v in batch.items()}
    y, a_bar, sq, _ = compute_target(agent, jb, alpha, settings, k_noise, k_next)

    # by hand: the same noise draws, the networks' outputs, the formula in NumPy
    a_bar_np = np.clip(batch["actions"] + 0.3 * np.asarray(jax.random.normal(k_noise, (4, A))), -1, 1)
    np.testing.assert_allclose(np.asarray(a_bar), a_bar_np, atol=1e-6)
    k_act, _ = jax.random.split(k_next)
    mean, log_std = (np.asarray(x, np.float64) for x in agent.policy(jb["next_observations"]))
    next_a, logp = _np_tanh_gaussian(mean, log_std, np.asarray(jax.random.normal(k_act, (4, A)), np.float64))
    q_next = np.asarray(agent.critic_values(agent.target_critic_params, jb["next_observations"],
                                            jnp.asarray(next_a, jnp.float32)), np.float64).min(0)
    v = q_next - (0.5 * logp if backup_entropy else 0.0)
    sq_np = ((batch["actions"] - a_bar_np) ** 2).sum(-1)
    y_np = batch["rewards"] - alpha * sq_np + 0.9 * (1 - batch["dones"]) * v
    np.testing.assert_allclose(np.asarray(sq), sq_np, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(y), y_np, rtol=1e-4, atol=1e-4)


def _dataset(n, seed):
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(n, O)).astype(np.float32)
    ends = np.zeros(n, bool)
    ends[9::10] = True
    return Dataset(obs, rng.uniform(-1, 1, (n, A)).astype(np.float32), rng.normal(size=n).astype(np.float32),
                   rng.normal(size=(n, O)).astype(np.float32), np.zeros(n, bool), ends, metadata={"source": "test"})


@pytest.fixture(scope="module")
def data():
    return _dataset(200, 0).with_mc_returns(0.99), _dataset(50, 1).with_mc_returns(0.99)


def _same(a, b):
    return jax.tree_util.tree_all(jax.tree_util.tree_map(lambda x, y: bool(np.array_equal(x, y)), a, b))


CFG = BOTOConfig(boto_steps=6, steps_per_call=3, batch_size=16)


def test_run_boto_calql_keeps_actor_frozen(data):
    agent = CQLAgent.create(CQLConfig(**TINY, calql=True, num_critics=4), O, A, seed=0)
    seen = []
    new, hist = run_boto(agent, *data, CFG, alpha=0.5, progress=False, callback=lambda s, a, m: seen.append(s))
    assert seen == [3, 6] and [h["step"] for h in hist] == [3, 6]
    assert {"critic_loss", "q_data", "q_perturbed", "q_uniform", "penalty", "sq_dist", "uniform_share"} <= set(hist[-1])
    assert all(math.isfinite(v) for v in hist[-1].values())
    assert _same(new.actor.params, agent.actor.params) and _same(new.temp.params, agent.temp.params)
    assert not _same(new.critic.params, agent.critic.params)
    assert not _same(new.target_critic_params, agent.target_critic_params)
    # resumable: 3 steps, then 3 more from step 3, equals 6 in one go
    half, _ = run_boto(agent, *data, CFG, alpha=0.5, num_steps=3, progress=False)
    rest, _ = run_boto(half, *data, CFG, alpha=0.5, start_step=3, progress=False)
    assert jax.tree_util.tree_all(jax.tree_util.tree_map(
        lambda x, y: bool(np.allclose(x, y, atol=1e-6)), rest.critic.params, new.critic.params))


def test_run_boto_cql_train_actor_option(data):
    agent = CQLAgent.create(CQLConfig(**TINY, num_critics=2), O, A, seed=0)
    new, hist = run_boto(agent, *data, BOTOConfig(boto_steps=2, steps_per_call=2, batch_size=16, train_actor=True),
                         alpha=0.0, progress=False)
    assert not _same(new.actor.params, agent.actor.params)
    assert "actor_loss" in hist[-1]


def test_run_boto_iql(data):
    agent = IQLAgent.create(IQLConfig(**TINY, value_hidden_dims=(8,)), O, A, seed=0)
    new, hist = run_boto(agent, *data, CFG, alpha=0.5, progress=False)
    assert _same(new.actor.params, agent.actor.params) and _same(new.value.params, agent.value.params)
    assert not _same(new.critic.params, agent.critic.params)
    assert math.isfinite(hist[-1]["critic_loss"])
    with pytest.raises(ConfigError):
        run_boto(agent, *data, BOTOConfig(boto_steps=2, train_actor=True), alpha=0.0, progress=False)


def test_alpha_outside_range_is_config_error(data):
    agent = IQLAgent.create(IQLConfig(**TINY, value_hidden_dims=(8,)), O, A, seed=0)
    with pytest.raises(ConfigError):
        run_boto(agent, *data, BOTOConfig(boto_steps=2), alpha=1.5, progress=False)
    with pytest.raises(ConfigError):
        boto_update(agent, data[0].sample(np.random.default_rng(0), 8), -1.01, BOTOConfig())


def test_refit_control_perturbs_nothing_so_alpha_has_no_effect():
    # noise "none" (the ablation's re-fit control): a_bar = a, the penalty is 0 and the target is
    # the plain soft backup, so BOTO steps at alpha -1 and +1 give the same critic bit for bit,
    # while with the paper's hybrid noise they do not (the control has power)
    agent = SACAgent.create(SACConfig(**TINY, num_critics=2, num_min_critics=2, subsample_replace=False), O, A, seed=2)
    rng = np.random.default_rng(3)
    batch = {"observations": rng.normal(size=(8, O)).astype(np.float32),
             "actions": rng.uniform(-0.9, 0.9, (8, A)).astype(np.float32),
             "rewards": rng.normal(size=8).astype(np.float32),
             "next_observations": rng.normal(size=(8, O)).astype(np.float32),
             "dones": np.zeros(8, np.float32)}
    jb = {k: jnp.asarray(v) for k, v in batch.items()}
    none = ObjectiveSettings.resolve(BOTOConfig(noise="none"), agent)
    y, a_bar, sq, info = compute_target(agent, jb, 1.0, none, jax.random.PRNGKey(0), jax.random.PRNGKey(1))
    np.testing.assert_array_equal(np.asarray(a_bar), batch["actions"])
    assert float(jnp.max(sq)) == 0.0 and not bool(info["uniform"].any())
    y_minus, *_ = compute_target(agent, jb, -1.0, none, jax.random.PRNGKey(0), jax.random.PRNGKey(1))
    np.testing.assert_array_equal(np.asarray(y), np.asarray(y_minus))
    for noise, same in (("none", True), ("hybrid", False)):
        cfg = BOTOConfig(noise=noise)
        lo, info_lo = boto_update(agent, batch, -1.0, cfg)
        hi, _ = boto_update(agent, batch, 1.0, cfg)
        assert _same(lo.critic.params, hi.critic.params) == same, noise
        if noise == "none":
            assert float(info_lo["penalty"]) == 0.0


def test_unknown_noise_kind_names_the_control():
    with pytest.raises(ConfigError, match="none"):
        BOTOConfig(noise="uniform").validate()

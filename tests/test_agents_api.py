"""Agent API: update_many == K x update, checkpoint round trip, warm start, errors."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from botorl.agents import agent_file
from botorl.agents.cql import CQLAgent, CQLConfig
from botorl.agents.iql import IQLAgent, IQLConfig
from botorl.agents.sac import SACAgent, SACConfig
from botorl.errors import BotorlError, ConfigError
from helpers import as_minibatches

O, A, B, K = 4, 2, 8, 3

MAKERS = {
    "sac_utd2": lambda: SACAgent.create(
        SACConfig(actor_hidden_dims=(16,), critic_hidden_dims=(16,), num_critics=3, max_target_backup=True,
                  num_backup_actions=2, backup_entropy=True), O, A, seed=0),
    "calql": lambda: CQLAgent.create(
        CQLConfig(actor_hidden_dims=(16,), critic_hidden_dims=(16,), num_critics=2, cql_n_actions=2, num_backup_actions=2,
                  calql=True), O, A, seed=0),
    "iql_dropout": lambda: IQLAgent.create(
        IQLConfig(actor_hidden_dims=(16,), critic_hidden_dims=(16,), value_hidden_dims=(16,), actor_dropout=0.1), O, A, seed=0),
}


UTD = {"sac_utd2": 2}  # the makers whose updates take their batch as this many critic minibatches


def batches(seed, utd=1):
    """K batches of B rows; at UTD u, each as u minibatches of B / u rows: (K, u, B / u, ...)."""
    r = np.random.default_rng(seed)
    flat = {
        "observations": r.normal(size=(K, B, O)).astype(np.float32),
        "actions": r.uniform(-0.9, 0.9, (K, B, A)).astype(np.float32),
        "rewards": r.normal(size=(K, B)).astype(np.float32),
        "next_observations": r.normal(size=(K, B, O)).astype(np.float32),
        "dones": (r.uniform(size=(K, B)) < 0.2).astype(np.float32),
        "mc_returns": r.normal(size=(K, B)).astype(np.float32),
    }
    return as_minibatches(flat, utd, axis=1) if utd > 1 else flat


def leaves_close(x, y, atol):
    lx, ly = jax.tree_util.tree_leaves(x), jax.tree_util.tree_leaves(y)
    assert len(lx) == len(ly)
    return max(float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)))) if np.size(a) else 0.0 for a, b in zip(lx, ly)) <= atol


@pytest.fixture(scope="module", params=list(MAKERS))
def stepped(request):
    """(agent0, agent after K single updates) -- the single-update path compiled once."""
    agent0 = MAKERS[request.param]()
    bs = batches(1, UTD.get(request.param, 1))
    agent = agent0
    for i in range(K):
        agent, _ = agent.update({k: v[i] for k, v in bs.items()})
    return agent0, agent, bs


def test_update_many_equals_k_updates(stepped):
    agent0, agent_k, bs = stepped
    many, info = agent0.update_many(bs)
    assert int(many.critic.step) == int(agent_k.critic.step)
    assert leaves_close(many, agent_k, 1e-6)
    assert all(np.isfinite(float(v)) for v in info.values())


def test_update_many_on_device_draws_its_batches_inside_the_call(stepped):
    # the device-sampled path = update_many on the batches sample_batches draws with the same key
    from botorl.agents.common import sample_batches, update_many_on_device

    agent0, _, bs = stepped
    rows = bs["rewards"].ndim  # the axes before a row's own: (K, B) or (K, u, B / u)
    arrays = {k: jax.numpy.asarray(v.reshape((K * B,) + v.shape[rows:])) for k, v in bs.items()}
    key = jax.random.PRNGKey(11)
    on_device, _ = update_many_on_device(agent0, arrays, key, K, B)
    host, _ = agent0.update_many(jax.device_get(sample_batches(arrays, key, K, B)))
    assert leaves_close(on_device, host, 1e-6)
    assert not leaves_close(on_device, agent0, 1e-6)  # it did train
    with pytest.raises(ConfigError, match="rewards"):
        update_many_on_device(agent0, {k: v for k, v in arrays.items() if k != "rewards"}, key, K, B)


def test_checkpoint_round_trip_is_bit_identical(stepped, tmp_path):
    _, agent, bs = stepped
    path = tmp_path / "agent.ckpt"
    agent_file.save(path, agent)
    template = type(agent).create(agent.config, O, A, seed=123)
    loaded = agent_file.load(path, like=template)
    one = {k: v[0] for k, v in bs.items()}
    a1, m1 = agent.update(one)
    a2, m2 = loaded.update(one)
    for x, y in zip(jax.tree_util.tree_leaves(a1), jax.tree_util.tree_leaves(a2)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert {k: float(v) for k, v in m1.items()} == {k: float(v) for k, v in m2.items()}


def test_checkpoint_bad_file(tmp_path, stepped):
    _, agent, _ = stepped
    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(BotorlError):
        agent_file.load(bad, like=agent)
    with pytest.raises(BotorlError):
        agent_file.load(tmp_path / "missing.ckpt", like=agent)
    # A checkpoint of another architecture.
    other = SACAgent.create(SACConfig(actor_hidden_dims=(4,), critic_hidden_dims=(4,), num_critics=2), O, A, seed=0)
    agent_file.save(tmp_path / "other.ckpt", other)
    with pytest.raises(BotorlError):
        agent_file.load(tmp_path / "other.ckpt", like=agent)


def test_sample_and_eval_actions_shapes_and_rng(stepped):
    _, agent, _ = stepped
    a1, agent2 = agent.sample_actions(np.zeros(O, np.float32))
    a2, _ = agent2.sample_actions(np.zeros(O, np.float32))
    assert a1.shape == (A,) and np.all(np.abs(a1) <= 1)
    assert not np.array_equal(a1, a2)  # rng advanced
    ev = agent.eval_actions(np.zeros((5, O), np.float32))
    assert ev.shape == (5, A)
    np.testing.assert_array_equal(ev, agent.eval_actions(np.zeros((5, O), np.float32)))


def test_acting_reads_only_the_actor_and_rng(stepped):
    """An action is a jitted call on the actor's parameters and the rng alone: the rest of the
    agent is neither passed in nor rebuilt (it cost 5 ms per antmaze env step,
    benchmarks/acting_cost.py), and the actions are those of the whole agent."""
    from botorl.agents.common import acting_view, sample_fn

    _, agent, _ = stepped
    view = acting_view(agent)
    assert view.critic is None and view.actor.opt_state is None
    assert len(jax.tree_util.tree_leaves(view)) == len(jax.tree_util.tree_leaves(agent.actor.params)) + 2  # + step, rng
    obs = np.linspace(-1, 1, 3 * O, dtype=np.float32).reshape(3, O)
    whole_actions, whole_rng = jax.jit(sample_fn)(agent, obs)
    actions, agent2 = agent.sample_actions(obs)
    np.testing.assert_array_equal(actions, whole_actions)
    np.testing.assert_array_equal(agent2.rng, whole_rng)
    assert agent2.critic is agent.critic  # the same arrays, not copies


def test_from_pretrained_takes_actor_and_critic(stepped):
    _, agent, _ = stepped
    n = agent.critic.params["members"]["Dense_0"]["kernel"].shape[0]
    cfg_fields = dict(actor_hidden_dims=(16,), critic_hidden_dims=(16,), num_critics=n)
    for f in ("actor_layer_norm", "critic_layer_norm", "state_dependent_std", "log_std_min", "log_std_max"):
        cfg_fields[f] = getattr(agent.config, f)
    sac = SACAgent.from_pretrained(agent, SACConfig(**cfg_fields))
    np.testing.assert_array_equal(sac.critic.params["members"]["Dense_0"]["kernel"],
                                  agent.critic.params["members"]["Dense_0"]["kernel"])
    for x, y in zip(jax.tree_util.tree_leaves(sac.actor.params), jax.tree_util.tree_leaves(agent.actor.params)):
        np.testing.assert_array_equal(x, y)
    # the pre-trained optimiser goes on (WSRL restores the whole agent)
    assert int(sac.critic.step) == int(agent.critic.step) > 0
    # an ensemble is never filled with copies of fewer pre-trained critics
    with pytest.raises(ConfigError, match="Pre-train with the fine-tuning ensemble size"):
        SACAgent.from_pretrained(agent, SACConfig(**{**cfg_fields, "num_critics": 2 * n}))
    with pytest.raises(ConfigError):
        SACAgent.from_pretrained(agent, SACConfig(**{**cfg_fields, "critic_hidden_dims": (8,)}))


def test_bad_config_and_batch():
    with pytest.raises(ConfigError):
        SACAgent.create(SACConfig(actor_objective="max"), O, A, seed=0)
    with pytest.raises(ConfigError):
        IQLAgent.create(IQLConfig(expectile=1.5), O, A, seed=0)
    agent = MAKERS["sac_utd2"]()
    with pytest.raises(ConfigError):
        agent.update({"observations": np.zeros((4, O))})

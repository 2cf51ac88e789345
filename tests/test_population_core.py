"""Populations: member parsing (botorl.configs.members), stacking and the mapped entry
points (botorl.agents.population, the BOTO update), per-member sampling and the replay buffer's member axis, the memory check
(botorl.pipeline.memory).

Independence is the property everything rests on: member i of a population computes what a
population of one (= the agent's own jitted function) computes for the same seed, to float
tolerance (vmapped matmuls may sum in another order: rtol 1e-4 after 20 updates).
"""

from __future__ import annotations

import numpy as np
import pytest

from botorl.agents import population as AP
from botorl.data.replay import ReplayBuffer
from botorl.errors import ConfigError
from botorl.pipeline import memory as P

O, A = 4, 2


@pytest.fixture(scope="module")
def dataset():
    from botorl.data.dataset import Dataset

    rng = np.random.default_rng(0)
    n = 300
    return Dataset(rng.normal(size=(n, O)), rng.uniform(-1, 1, (n, A)), rng.normal(size=n), rng.normal(size=(n, O)),
                   rng.random(n) < 0.05).with_mc_returns(0.99)


def _calql(seed):
    from botorl.agents.cql import CQLAgent, CQLConfig

    cfg = CQLConfig(actor_hidden_dims=(16,), critic_hidden_dims=(16,), num_critics=2, cql_n_actions=2,
                    num_backup_actions=2, cql_lagrange=False, calql=True)
    return CQLAgent.create(cfg, O, A, seed)


def _iql(seed):
    from botorl.agents.iql import IQLAgent, IQLConfig

    return IQLAgent.create(IQLConfig(actor_hidden_dims=(16,), critic_hidden_dims=(16,), value_hidden_dims=(16,)), O, A, seed)


# ------------------------------------------------------------------ members
def test_parse_seeds_and_alphas():
    from botorl.configs import members as P

    assert P.parse_seeds("0-3") == [0, 1, 2, 3]
    assert P.parse_seeds("0-2,7") == [0, 1, 2, 7]
    assert P.parse_alphas("-1:1:0.25") == [-1.0, -0.75, -0.5, -0.25, 0.0, 0.25, 0.5, 0.75, 1.0]
    assert P.parse_alphas("-0.5,0,0.5") == [-0.5, 0.0, 0.5]
    for bad in ("0-3,2", "1,1", "x", "3-1"):
        with pytest.raises(ConfigError):
            P.parse_seeds(bad)
    for bad in ("0.5,0.5", "-1.5", "0,2", "1:-1:0.5", "a"):
        with pytest.raises(ConfigError):
            P.parse_alphas(bad)
    ms = P.make_members([0, 1], [-0.5, 0.5])
    assert [(m.seed, m.alpha) for m in ms] == [(0, -0.5), (1, -0.5), (0, 0.5), (1, 0.5)]
    assert ms[0].name == "alpha-0.50-seed0" and P.Member(3).name == "seed3"


# ------------------------------------------------------------------ stacking and vmapped updates
def test_stack_unstack_roundtrip():
    import jax

    agents = [_iql(s) for s in (1, 2, 3)]
    pop = AP.stack(agents)
    assert AP.population_size(pop) == 3
    for a, b in zip(agents, AP.unstack(pop)):
        for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_updates_split_members_over_the_cpu_devices(dataset):
    """conftest gives the process 2 CPU devices: a population's update runs its members on
    both (even split for 4 members; 3 members padded to 4 and kept on both), the agents stay
    where the update put them (one compile per population size), and member 1 is still the
    1-member population's member."""
    import jax

    assert len(jax.local_devices()) == 2 and AP.host_shards(1) == 1 and AP.host_shards(3) == 2
    one = AP.stack([_calql(3)])
    b1 = dataset.sample_members([np.random.default_rng([3, 1])], 16, 5)
    one, m1 = AP.update_many(one, b1)
    for seeds in ([5, 3, 8, 9], [5, 3, 8]):
        pop = AP.stack([_calql(s) for s in seeds])
        rngs = [np.random.default_rng([s, 1]) for s in seeds]
        before = AP.jit_update_many._cache_size()
        for _ in range(2):
            pop, m = AP.update_many(pop, dataset.sample_members(rngs, 16, 5))
        assert AP.jit_update_many._cache_size() - before == 1
        leaf = jax.tree_util.tree_leaves(pop)[0]
        assert len(leaf.sharding.device_set) == 2
        if len(seeds) == 4:  # split, not copied: each device holds 2 members
            assert {s.data.shape[0] for s in leaf.addressable_shards} == {2}
        pop_first = AP.stack([_calql(s) for s in seeds])
        pop_first, m = AP.update_many(pop_first, dataset.sample_members(
            [np.random.default_rng([s, 1]) for s in seeds], 16, 5))
        np.testing.assert_allclose(np.asarray(m["critic_loss"])[1], np.asarray(m1["critic_loss"])[0], rtol=1e-5)
        for x, y in zip(jax.tree_util.tree_leaves(AP.member_of(pop_first, 1)), jax.tree_util.tree_leaves(one)):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y)[0], rtol=1e-5, atol=1e-6)


def test_cpu_device_count_setting(monkeypatch):
    from botorl.jaxsetup import cpu_device_count

    monkeypatch.setenv("BOTORL_CPU_DEVICES", "3")
    assert cpu_device_count() == 3
    for bad in ("two", "0"):
        monkeypatch.setenv("BOTORL_CPU_DEVICES", bad)
        with pytest.raises(ConfigError, match="BOTORL_CPU_DEVICES"):
            cpu_device_count()
    monkeypatch.delenv("BOTORL_CPU_DEVICES")
    import os

    assert cpu_device_count() == len(os.sched_getaffinity(0))


@pytest.mark.parametrize("make", [_calql, _iql], ids=["calql", "iql"])
def test_member_equals_population_of_one(make, dataset):
    """Member (seed 3) of a population of 3 and a population of one with seed 3 draw the same
    batches and actions and reach the same losses; one compile per population size."""
    seeds = [5, 3, 8]
    pop, one = AP.stack([make(s) for s in seeds]), AP.stack([make(3)])
    rngs = [np.random.default_rng([s, 1]) for s in seeds]
    rng1 = [np.random.default_rng([3, 1])]
    before = AP.jit_update_many._cache_size()
    for _ in range(4):
        b, b1 = dataset.sample_members(rngs, 16, 5), dataset.sample_members(rng1, 16, 5)
        np.testing.assert_array_equal(b["observations"][1], b1["observations"][0])
        pop, m = AP.update_many(pop, b)
        one, m1 = AP.update_many(one, b1)
        np.testing.assert_allclose(np.asarray(m["critic_loss"])[1], np.asarray(m1["critic_loss"])[0], rtol=1e-4)
    assert AP.jit_update_many._cache_size() - before <= 2  # N = 3 and N = 1, each once
    obs = dataset.observations[:3]
    a, pop = AP.sample(pop, obs)
    a1, one = AP.sample(one, obs[1:2])
    np.testing.assert_allclose(np.asarray(a)[1], np.asarray(a1)[0], atol=1e-5)
    np.testing.assert_allclose(np.asarray(AP.eval_actions(pop, obs[None].repeat(3, 0)))[1],
                               np.asarray(AP.eval_actions(one, obs[None]))[0], atol=1e-5)
    # a population of one is the agent's own jitted update, bit for bit
    plain = make(3)
    r = np.random.default_rng([3, 1])
    for _ in range(4):
        plain, mp = plain.update_many(dataset.sample(r, 16, num_batches=5))
    np.testing.assert_array_equal(np.asarray(mp["critic_loss"]), np.asarray(m1["critic_loss"])[0])


def test_boto_each_member_its_alpha(dataset):
    from botorl.boto.config import BOTOConfig
    from botorl.boto.objective import ObjectiveSettings, boto_update_many, population_update_many
    from botorl.boto.phase import boto_batches

    seeds, alphas = [0, 1, 2], np.array([-1.0, 0.0, 0.5], np.float32)
    agents = [_calql(s) for s in seeds]
    settings = ObjectiveSettings.resolve(BOTOConfig(), agents[0])
    warm = [None] * len(seeds)
    rngs = [np.random.default_rng([s, 0]) for s in seeds]
    b = boto_batches(dataset, warm, rngs, 16, 3)
    pop, m = population_update_many(AP.stack(agents), b, alphas, settings)
    for i, s in enumerate(seeds):
        bi = dataset.sample(np.random.default_rng([s, 0]), 16, num_batches=3)
        np.testing.assert_array_equal(b["actions"][i], bi["actions"])
        _, mi = boto_update_many(agents[i], bi, float(alphas[i]), settings)
        np.testing.assert_allclose(np.asarray(m["critic_loss"])[i], float(mi["critic_loss"]), rtol=1e-4)
        np.testing.assert_allclose(np.asarray(m["penalty"])[i], float(mi["penalty"]), rtol=1e-4, atol=1e-6)


# ------------------------------------------------------------------ sampling and replay
def test_union_sampling_matches_concat(dataset):
    from botorl.boto.phase import boto_batches
    from botorl.data.dataset import Dataset

    rng = np.random.default_rng(1)
    warm = [Dataset(rng.normal(size=(40, O)), rng.uniform(-1, 1, (40, A)), rng.normal(size=40),
                    rng.normal(size=(40, O)), rng.random(40) < 0.1) for _ in range(2)]
    b = boto_batches(dataset, warm, [np.random.default_rng([s, 7]) for s in (4, 9)], 64, 3)
    for i, s in enumerate((4, 9)):
        ref = dataset.concat(warm[i]).sample(np.random.default_rng([s, 7]), 64, num_batches=3)
        for k in ("observations", "actions", "rewards", "next_observations", "dones"):
            np.testing.assert_array_equal(b[k][i], ref[k])


def test_member_replay_matches_replay_buffer(dataset):
    from helpers import sample_mixed

    rng = np.random.default_rng(2)
    n, cap = 3, 50
    pop = ReplayBuffer(cap, O, A, members=n)
    singles = [ReplayBuffer(cap, O, A) for _ in range(n)]
    for _ in range(70):  # wraps around
        o, a, r, o2, d = rng.normal(size=(n, O)), rng.uniform(-1, 1, (n, A)), rng.normal(size=n), \
            rng.normal(size=(n, O)), rng.random(n) < 0.1
        pop.insert(o, a, r, o2, d)
        for i, buf in enumerate(singles):
            buf.insert(o[i], a[i], r[i], o2[i], d[i])
    seeds = [11, 12, 13]
    got = pop.sample_members([np.random.default_rng(s) for s in seeds], 20, 4, offline=dataset, offline_ratio=0.5)
    got2 = pop.sample_members([np.random.default_rng(s) for s in seeds], 20)
    for i, s in enumerate(seeds):
        ref = sample_mixed([dataset, singles[i]], [0.5, 0.5], np.random.default_rng(s), 20, num_batches=4)
        ref2 = singles[i].sample(np.random.default_rng(s), 20)
        for k in ref:
            np.testing.assert_array_equal(got[k][i], ref[k])
            np.testing.assert_array_equal(got2[k][i], ref2[k])
    back = ReplayBuffer.from_state_dict(pop.state_dict())
    for k in ("observations", "dones"):
        np.testing.assert_array_equal(getattr(back, k), getattr(pop, k))
    assert (back.size, back.insert_index) == (pop.size, pop.insert_index)


def test_sample_active_draws_each_active_member_as_a_single_run(dataset):
    """The fine-tuning batch of a population with an inactive member (Cal-QL online before its
    first episode ends): each active member draws exactly what its single run draws, from
    its own rows (the flat gather must index the right member), the inactive one nothing."""
    from helpers import FinishedRows, sample_mixed

    rng = np.random.default_rng(4)
    n, cap = 3, 40
    pop = ReplayBuffer(cap, O, A, members=n)
    singles = [ReplayBuffer(cap, O, A) for _ in range(n)]
    for t in range(55):  # wraps around; member i ends an episode every 7 + i steps
        o, a, r, o2, d = rng.normal(size=(n, O)), rng.uniform(-1, 1, (n, A)), rng.normal(size=n), \
            rng.normal(size=(n, O)), np.zeros(n)
        pop.insert(o, a, r, o2, d)
        for i, buf in enumerate(singles):
            buf.insert(o[i], a[i], r[i], o2[i], d[i])
            if (t + 1) % (7 + i) == 0:
                buf.end_episode()
                pop.end_episode(i)
    active = [True, False, True]
    seeds = [21, 22, 23]
    for offline, ratio, finished in ((dataset, 0.5, False), (None, 0.0, True)):
        rngs = [np.random.default_rng(s) for s in seeds]
        got = pop.sample_members(rngs, 16, 3, active=active, finished=finished, offline=offline, offline_ratio=ratio)
        for i, s in enumerate(seeds):
            if not active[i]:
                assert all(not got[k][i].any() for k in got)
                assert rngs[i].integers(0, 10**9) == np.random.default_rng(s).integers(0, 10**9)  # not advanced
                continue
            rows = FinishedRows(singles[i]) if finished else singles[i]
            ref = (sample_mixed([offline, rows], [ratio, 1 - ratio], np.random.default_rng(s), 16, num_batches=3)
                   if offline is not None else rows.sample(np.random.default_rng(s), 16, num_batches=3))
            for k in ref:
                np.testing.assert_array_equal(got[k][i], ref[k])


# ------------------------------------------------------------------ memory
def test_memory_estimate_and_check():
    parts = P.estimate_memory(num_members=8, agent_bytes=10**6, buffer_rows=1000, warmup_rows=100, obs_dim=4,
                              action_dim=2, batch_rows=256, activation_floats=10**5, offline_bytes=10**7)
    assert parts["total"] == sum(v for k, v in parts.items() if k != "total")
    P.check_memory(parts, 8, available=(10**9, "test memory"))
    with pytest.raises(ConfigError, match="fewer members"):
        P.check_memory(parts, 8, available=(2 * 10**7, "test memory"))
    # each member's environments count: 8 x 100 MB does not fit in 0.5 GB, and the message names them
    with_envs = P.estimate_memory(num_members=8, agent_bytes=10**6, buffer_rows=1000, warmup_rows=100, obs_dim=4,
                                  action_dim=2, batch_rows=256, activation_floats=10**5, offline_bytes=10**7,
                                  env_bytes_per_member=10**8)
    assert with_envs["environments"] == 8 * 10**8 and with_envs["total"] == parts["total"] + 8 * 10**8
    with pytest.raises(ConfigError, match="eval.num_envs"):
        P.check_memory(with_envs, 8, available=(5 * 10**8, "test memory"))


def test_env_bytes_measures_what_an_env_holds():
    import mmap

    class Heavy:  # an env that holds 16 MiB once made and reset
        def __init__(self):
            self.state = None

        def reset(self, seed=None):
            # fresh pages, every one touched: heap memory freed earlier in this process (other
            # tests) could be handed back already resident and hide the growth env_bytes measures
            self.state = mmap.mmap(-1, 2**24)
            np.frombuffer(self.state, np.uint8)[::4096] = 1

        def close(self):
            self.state.close()

    per = P.env_bytes(lambda i: Heavy(), probes=5)
    assert 15 * 2**20 <= per <= 20 * 2**20, per / 2**20

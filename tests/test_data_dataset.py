"""Dataset: construction, MC returns (hand-computed), reward transform, sampling, validate."""

from __future__ import annotations

import numpy as np
import pytest

from botorl.agents.common import sample_batches
from botorl.data.dataset import ACTION_CLIP, BATCH_KEYS, Dataset, RewardTransform, validate
from botorl.errors import DataFormatError


def make(rewards, terminals, ends, obs_dim=3, act=None, **kw):
    n = len(rewards)
    obs = np.arange(n * obs_dim, dtype=np.float32).reshape(n, obs_dim)
    act = np.zeros((n, 2), np.float32) if act is None else act
    return Dataset(obs, act, rewards, obs + 1, terminals, ends, metadata={"source": "test.hdf5"}, **kw)


def test_mc_returns_hand_computed():
    g = 0.9
    # episode 1: 3 steps, truncated; episode 2: 2 steps, terminal at the end.
    ds = make([1.0, 0.0, 2.0, 0.5, 1.0], [0, 0, 0, 0, 1], [0, 0, 1, 0, 1]).with_mc_returns(g)
    want = [1 + g * (0 + g * 2), 0 + g * 2, 2, 0.5 + g * 1, 1]
    np.testing.assert_allclose(ds.mc_returns, want, rtol=1e-6)


def test_mc_terminal_inside_episode_restarts_sum():
    g = 0.5
    # Cal-QL adroit: [-1, -1, 0, 0] with every 0 terminal, one episode.
    ds = make([-1.0, -1.0, 0.0, 0.0], [0, 0, 1, 1], [0, 0, 0, 1]).with_mc_returns(g, sparse_negative_reward=-1.0)
    np.testing.assert_allclose(ds.mc_returns, [-1 + g * -1, -1, 0, 0], rtol=1e-6)


def test_mc_never_succeeding_sparse_episode():
    g = 0.99
    ds = make([-1.0, -1.0, -1.0, -1.0, 0.0], [0, 0, 0, 0, 1], [0, 0, 1, 0, 1])
    out = ds.with_mc_returns(g, sparse_negative_reward=-1.0)
    np.testing.assert_allclose(out.mc_returns[:3], -100.0, rtol=1e-5)  # r_neg / (1 - gamma)
    np.testing.assert_allclose(out.mc_returns[3:], [-1.0, 0.0], rtol=1e-6)
    # Without the sparse flag the finite discounted sum is used.
    np.testing.assert_allclose(ds.with_mc_returns(g).mc_returns[0], -1 - g - g * g, rtol=1e-6)


def test_mc_infinite_horizon_kitchen_style():
    g = 0.5
    ds = make([1.0, 2.0], [0, 0], [0, 1]).with_mc_returns(g, infinite_horizon=True)
    tail = 2.0 / (1 - g)
    np.testing.assert_allclose(ds.mc_returns, [1 + g * (2 + g * tail), 2 + g * tail], rtol=1e-6)


def test_reward_transform_recomputes_mc_returns():
    g = 0.99
    ds = make([-1.0, -1.0, 0.0, -1.0], [0, 0, 1, 0], [0, 0, 1, 1]).with_mc_returns(g, sparse_negative_reward=-1.0)
    out = ds.with_reward_transform(RewardTransform(10.0, 5.0))
    np.testing.assert_allclose(out.rewards, [-5, -5, 5, -5])
    direct = make([-5.0, -5.0, 5.0, -5.0], [0, 0, 1, 0], [0, 0, 1, 1]).with_mc_returns(g, sparse_negative_reward=-5.0)
    np.testing.assert_allclose(out.mc_returns, direct.mc_returns, rtol=1e-6)
    assert out.mc_returns[3] == pytest.approx(-500.0)
    assert RewardTransform(10, -5)(np.array([0.0, 1.0])).tolist() == [-5.0, 5.0]


def test_actions_clipped_and_validate_tolerance():
    act = np.array([[1.0, -1.0], [0.5, 1.0005]], np.float32)
    ds = make([0.0, 0.0], [0, 0], [0, 1], act=act)
    assert np.abs(ds.actions).max() <= ACTION_CLIP
    validate(ds, action_tolerance=1e-3)  # 1.0005 is within 1e-3
    with pytest.raises(DataFormatError, match=r"test\.hdf5.*actions reach magnitude 1\.0005"):
        validate(ds, action_tolerance=1e-4)
    big = make([0.0], [0], [1], act=np.array([[3.0, 0.0]], np.float32))
    with pytest.raises(DataFormatError, match="outside"):
        validate(big)


@pytest.mark.parametrize("field", ["observations", "rewards", "actions"])
@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_validate_rejects_non_finite(field, value):
    ds = make([0.0, 1.0, 2.0], [0, 0, 0], [0, 0, 1])
    arr = getattr(ds, field).copy()
    arr.reshape(-1)[2] = value
    kw = {"act": arr} if field == "actions" else {}
    if field == "observations":
        bad = Dataset(arr, ds.actions, ds.rewards, ds.next_observations, ds.terminals, metadata={"source": "test.hdf5"})
    elif field == "rewards":
        bad = make(arr, [0, 0, 0], [0, 0, 1])
    else:
        bad = make([0.0, 1.0, 2.0], [0, 0, 0], [0, 0, 1], **kw)
    with pytest.raises(DataFormatError, match=r"test\.hdf5"):
        validate(bad)


def test_validate_dims_and_mismatched_lengths():
    ds = make([0.0, 1.0], [0, 0], [0, 1])
    validate(ds, obs_dim=3, action_dim=2)
    with pytest.raises(DataFormatError, match="3 dimensions but the task expects 29"):
        validate(ds, obs_dim=29)
    with pytest.raises(DataFormatError, match="expects 8"):
        validate(ds, action_dim=8)
    with pytest.raises(DataFormatError, match="mismatched"):
        Dataset(np.zeros((3, 2)), np.zeros((2, 1)), np.zeros(3), np.zeros((3, 2)), np.zeros(3))


def test_sample_and_episodes_and_concat():
    ds = make(np.arange(6, dtype=np.float32), [0, 0, 1, 0, 0, 0], [0, 0, 1, 0, 0, 1])
    b = ds.sample(np.random.default_rng(0), 64)
    assert set(b) == set(BATCH_KEYS)
    assert all(v.dtype == np.float32 for v in b.values())
    assert b["observations"].shape == (64, 3) and b["rewards"].shape == (64,)
    # Rows stay consistent: reward i belongs to observation row i.
    np.testing.assert_allclose(b["observations"][:, 0] / 3, b["rewards"])
    np.testing.assert_array_equal(b["dones"], (b["rewards"] == 2).astype(np.float32))
    np.testing.assert_array_equal(b["mc_returns"], 0.0)
    k = ds.sample(np.random.default_rng(0), 8, num_batches=3)
    assert k["actions"].shape == (3, 8, 2)
    eps = list(ds.episodes())
    assert [len(e["rewards"]) for e in eps] == [3, 3]
    both = ds.concat(ds)
    assert len(both) == 12 and both.num_episodes == 4
    st = ds.stats()
    assert st["episodes"] == 2 and st["return_mean"] == pytest.approx((0 + 1 + 2 + 3 + 4 + 5) / 2)


def test_device_sampling_inside_jit_and_scan():
    import jax

    ds = make(np.arange(10, dtype=np.float32), np.zeros(10), np.zeros(10)).with_mc_returns(0.9)
    arrays = ds.to_device()

    @jax.jit
    def run(arrays, key):
        def body(carry, k):
            b = sample_batches(arrays, k, 1, 4)
            return carry + b["rewards"].sum(), b["observations"][0, :, 0] / 3 - b["rewards"][0]

        return jax.lax.scan(body, 0.0, jax.random.split(key, 5))

    total, diffs = run(arrays, jax.random.PRNGKey(0))
    np.testing.assert_allclose(np.asarray(diffs), 0.0, atol=1e-5)  # rows not mixed up
    many = sample_batches(arrays, jax.random.PRNGKey(1), 3, 4)
    assert many["next_observations"].shape == (3, 4, 3)

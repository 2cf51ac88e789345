"""ReplayBuffer: wraparound, batched insert, checkpoint round trip, exact mixing counts."""

from __future__ import annotations

import numpy as np
import pytest

from botorl.data.dataset import Dataset
from botorl.data.replay import ReplayBuffer, split_counts
from helpers import sample_mixed


def row(i):
    return dict(observation=np.full(2, i), action=np.full(1, 0.1), reward=float(i), next_observation=np.full(2, i + 1), done=i % 2)


def test_wraparound_keeps_latest():
    buf = ReplayBuffer(4, 2, 1)
    for i in range(6):
        buf.insert(**row(i))
    assert len(buf) == 4 and buf.insert_index == 2 and buf.total_inserted == 6
    assert sorted(buf.rewards.tolist()) == [2, 3, 4, 5]
    np.testing.assert_array_equal(buf.rewards, [4, 5, 2, 3])


def test_insert_batch_matches_single_inserts():
    a, b = ReplayBuffer(5, 2, 1), ReplayBuffer(5, 2, 1)
    for i in range(3):
        a.insert(**row(i))
        b.insert(**row(i))
    n = 9  # more than the capacity, crossing the end of the ring
    rows = [row(i) for i in range(3, 3 + n)]
    for r in rows:
        a.insert(**r)
    b.insert_batch(
        [r["observation"] for r in rows], [r["action"] for r in rows], [r["reward"] for r in rows],
        [r["next_observation"] for r in rows], [r["done"] for r in rows],
    )
    for k in ("observations", "actions", "rewards", "next_observations", "dones"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    assert (a.size, a.insert_index, a.total_inserted) == (b.size, b.insert_index, b.total_inserted)


def test_state_dict_round_trip():
    buf = ReplayBuffer(4, 2, 1)
    for i in range(6):
        buf.insert(**row(i))
    state = buf.state_dict()
    back = ReplayBuffer.from_state_dict({k: np.asarray(v) for k, v in state.items()})
    for k in ("observations", "rewards", "dones"):
        np.testing.assert_array_equal(getattr(back, k), getattr(buf, k))
    assert back.insert_index == buf.insert_index
    back.insert(**row(9))
    buf.insert(**row(9))
    np.testing.assert_array_equal(back.rewards, buf.rewards)


def test_mixed_sampling_exact_counts():
    assert split_counts([0.5, 0.5], 256) == [128, 128]
    assert split_counts([1, 2], 10) == [3, 7]
    assert sum(split_counts([0.3, 0.3, 0.4], 7)) == 7
    buf = ReplayBuffer(10, 2, 1)
    for i in range(5):
        buf.insert(observation=np.zeros(2), action=np.zeros(1), reward=1.0, next_observation=np.zeros(2), done=0)
    n = 20
    ds = Dataset(np.ones((n, 2)), np.zeros((n, 1)), -np.ones(n), np.ones((n, 2)), np.zeros(n)).with_mc_returns(0.9)
    rng = np.random.default_rng(0)
    b = sample_mixed([ds, buf], [0.5, 0.5], rng, 256)
    assert (b["rewards"] == -1).sum() == 128 and (b["rewards"] == 1).sum() == 128
    assert np.all(b["mc_returns"][128:] == 0) and np.all(b["mc_returns"][:128] < 0)
    k = sample_mixed([ds, buf], [0.25, 0.75], rng, 8, num_batches=3)
    assert k["rewards"].shape == (3, 8) and np.all((k["rewards"] == -1).sum(axis=1) == 2)
    # An empty source gives its share to the others.
    empty = ReplayBuffer(4, 2, 1)
    b = sample_mixed([ds, empty], [0.5, 0.5], rng, 16)
    assert np.all(b["rewards"] == -1) and len(b["rewards"]) == 16


def test_insert_dataset_keeps_mc_returns():
    n = 6
    ds = Dataset(np.zeros((n, 3)), np.zeros((n, 2)), np.ones(n), np.zeros((n, 3)), np.zeros(n)).with_mc_returns(0.5)
    buf = ReplayBuffer(10, 3, 2)
    buf.insert_dataset(ds)
    np.testing.assert_allclose(buf.mc_returns[:n], ds.mc_returns)
    assert len(buf) == n
    with pytest.raises(Exception):
        ReplayBuffer(10, 4, 2).insert_dataset(ds)

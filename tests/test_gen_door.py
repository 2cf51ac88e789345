"""The door-binary-local generator on a few steps (tiny BC)."""

from __future__ import annotations

import numpy as np
import pytest

from botorl.data.generators import door
from botorl.errors import DatasetNotFoundError


def _expected_demo_rows(path) -> int:
    """All 25 demos kept: T - 1 transitions each, a successful one cut after its last success."""
    with np.load(path) as f:
        obs, lengths = f["observations"], f["episode_lengths"]
    total, start = 0, 0
    for n in lengths:
        ok = np.nonzero(obs[start + 1 : start + n, 28] >= 1.35)[0]
        total += int(ok[-1]) + 1 if len(ok) else int(n) - 1
        start += n
    return total


@pytest.fixture(scope="module")
def small(door_demos_path):
    return door.generate(400, seed=0, progress=False, demos_path=door_demos_path, bc_steps=100)


def test_binary_labels_and_cal_ql_cuts(small):
    ds = small
    assert ds.obs_dim == 39 and ds.action_dim == 28
    assert set(np.unique(ds.rewards)) <= {-1.0, 0.0}
    success = ds.next_observations[:, 28] >= 1.35
    np.testing.assert_array_equal(ds.rewards == 0.0, success)
    np.testing.assert_array_equal(ds.terminals, success)
    # a successful trajectory ends on its last success step
    for ep in ds.episodes():
        if ep["terminals"].any():
            assert ep["terminals"][-1]
    md = ds.metadata
    assert md["demos_total"] == 25 and md["bc_episodes"] >= 2
    assert 0.0 <= md["bc_success_rate"] <= 1.0
    n_demo = int(ds.infos["is_demo"].sum())
    assert n_demo == _expected_demo_rows(md["source"].split("demos=")[1].rstrip(")"))
    assert len(ds) - n_demo >= 400 - 200  # the rollouts (at most the cut of successful ones)


def test_demos_are_used_as_recorded(door_demos_path, small):
    with np.load(door_demos_path) as f:
        obs = f["observations"]
    np.testing.assert_allclose(small.observations[:50], obs[:50], atol=1e-6)
    np.testing.assert_allclose(small.next_observations[:50], obs[1:51], atol=1e-6)


def test_drop_unsuccessful_keeps_only_successful_demos(door_demos_path):
    ds = door.generate(0, seed=0, progress=False, demos_path=door_demos_path, drop_unsuccessful=True)
    eps = list(ds.episodes())
    assert 5 <= len(eps) <= 10
    assert all(ep["terminals"][-1] for ep in eps)


def test_missing_demos_say_how_to_point_at_them(monkeypatch, tmp_path):
    monkeypatch.delenv(door.ENV_VAR, raising=False)
    monkeypatch.setattr(door, "SHIPPED_DEMOS", tmp_path / "not-installed.npz")  # an install without the asset
    with pytest.raises(DatasetNotFoundError, match="BOTORL_DOOR_DEMOS"):
        door.generate(10, 0, progress=False)
    with pytest.raises(DatasetNotFoundError, match="does not exist"):
        door.generate(10, 0, progress=False, demos_path=tmp_path / "nope.npz")

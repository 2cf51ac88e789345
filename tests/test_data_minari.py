"""botorl writes Minari datasets that minari.load_dataset reads; round trip through load_minari."""

from __future__ import annotations

import numpy as np
import pytest

from botorl.data.dataset import Dataset
from botorl.data.loaders import load_minari
from botorl.data.minari_io import write_minari
from botorl.errors import BotorlError, ConfigError


def small_dataset():
    # Two episodes: a continuous one ending in a terminal with a mid-episode terminal,
    # and a truncated one with a discontinuity inside (written as a split, joined on load).
    obs = np.arange(8, dtype=np.float32)[:, None] * np.ones((1, 3), np.float32)
    nobs = obs + 1
    nobs[5] = 99.0  # not equal to obs[6]
    term = np.array([0, 1, 0, 1, 0, 0, 0, 0], bool)
    ends = np.array([0, 0, 0, 1, 0, 0, 0, 1], bool)
    return Dataset(obs, np.full((8, 2), 0.3), np.arange(8.0), nobs, term, ends,
                   infos={"success": term.astype(np.float32)}, metadata={"source": "mem"})


def test_write_then_minari_load_dataset(tmp_path, monkeypatch):
    import minari

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    ds = small_dataset()
    path = write_minari(ds, "botorl/unit/steps8-seed0-v0", metadata={"generator": "unit", "steps": 8, "seed": 0})
    assert path == tmp_path / "botorl" / "unit" / "steps8-seed0-v0"
    assert not any(p.name.startswith(".botorl-tmp") for p in tmp_path.iterdir())  # temp dir cleaned up
    m = minari.load_dataset("botorl/unit/steps8-seed0-v0")
    assert m.total_steps == 8 and m.total_episodes == 3  # the discontinuity forces a split
    ep = m[0]
    np.testing.assert_array_equal(ep.observations[:, 0], [0, 1, 2, 3, 4])
    np.testing.assert_array_equal(ep.terminations, [0, 1, 0, 1])
    np.testing.assert_array_equal(ep.infos["success"], [0, 0, 1, 0, 1])
    assert m.storage.metadata["botorl_metadata"]
    back = load_minari("botorl/unit/steps8-seed0-v0")
    for k in ("observations", "actions", "rewards", "next_observations", "terminals", "episode_ends"):
        np.testing.assert_array_equal(getattr(back, k), getattr(ds, k), err_msg=k)
    np.testing.assert_array_equal(back.infos["success"], ds.infos["success"])
    assert back.metadata["botorl"]["generator"] == "unit" and back.metadata["botorl"]["seed"] == 0
    (path / "botorl_flat.npz").unlink()  # the Minari data alone give the same rows
    slow = load_minari("botorl/unit/steps8-seed0-v0")
    for k in ("observations", "actions", "rewards", "next_observations", "terminals", "episode_ends"):
        np.testing.assert_array_equal(getattr(slow, k), getattr(ds, k), err_msg=k)
    assert slow.metadata["botorl"]["seed"] == 0
    with pytest.raises(BotorlError, match="already exists"):
        write_minari(ds, "botorl/unit/steps8-seed0-v0")
    write_minari(ds.with_reward_transform(2.0, 0.0), "botorl/unit/steps8-seed0-v0", overwrite=True)
    assert load_minari("botorl/unit/steps8-seed0-v0").rewards[1] == 2.0


def test_write_to_path_and_bad_id(tmp_path):
    ds = small_dataset()
    p = write_minari(ds, path=tmp_path / "mine-v3")
    assert (p / "data" / "main_data.hdf5").exists()
    assert len(load_minari(p)) == 8
    with pytest.raises(ConfigError, match="not a valid Minari dataset id"):
        write_minari(ds, path=tmp_path / "no.version")

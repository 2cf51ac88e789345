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


def many_episode_dataset(n_eps=400, seed=0):
    # Random episode lengths 1..40 (many of length 1, as pointmaze's goal visits), a
    # discontinuity inside one episode, terminal and truncated ends, a success info.
    rng = np.random.default_rng(seed)
    lengths = np.where(rng.random(n_eps) < 0.4, 1, rng.integers(1, 41, n_eps))
    n = int(lengths.sum())
    obs = rng.normal(size=(n, 4)).astype(np.float32)
    nobs = np.roll(obs, -1, axis=0)
    ends = np.zeros(n, bool)
    ends[np.cumsum(lengths) - 1] = True
    nobs[ends] = rng.normal(size=(int(ends.sum()), 4))  # last next_observation of each episode
    term = ends & (rng.random(n) < 0.5)
    jump_row = int(np.flatnonzero(lengths > 5)[3])  # a split inside this episode
    nobs[int(np.cumsum(lengths)[jump_row - 1]) + 2] += 1.0
    return Dataset(obs, rng.uniform(-1, 1, (n, 2)), rng.normal(size=n), nobs, term, ends,
                   infos={"success": term.astype(np.float32)}, metadata={"source": "mem"})


def test_fast_writer_matches_minari_writer(tmp_path, monkeypatch):
    """The h5py writer gives what minari.create_dataset_from_buffers gives, as Minari reads it."""
    import minari

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    ds = many_episode_dataset()
    write_minari(ds, "botorl/unit/fast-v0", metadata={"seed": 0})
    write_minari(ds, "botorl/unit/ref-v0", metadata={"seed": 0}, _minari_writer=True)
    fast, ref = minari.load_dataset("botorl/unit/fast-v0"), minari.load_dataset("botorl/unit/ref-v0")
    assert fast.total_episodes == ref.total_episodes == 401  # 400 + the split
    assert fast.total_steps == ref.total_steps == len(ds)
    mf, mr = fast.storage.metadata, ref.storage.metadata
    assert set(mf) == set(mr)
    for k in set(mr) - {"dataset_id", "dataset_size", "description"}:
        assert mf[k] == mr[k], k
    for ef, er in zip(fast.iterate_episodes(), ref.iterate_episodes(), strict=True):
        assert ef.id == er.id
        for k in ("observations", "actions", "rewards", "terminations", "truncations"):
            a, b = getattr(ef, k), getattr(er, k)
            assert a.dtype == b.dtype and a.shape == b.shape, k
            np.testing.assert_array_equal(a, b, err_msg=k)
        assert set(ef.infos) == set(er.infos)
        for k in er.infos:
            np.testing.assert_array_equal(ef.infos[k], er.infos[k], err_msg=k)
    assert list(fast.storage.get_episode_metadata([0, 400])) == list(ref.storage.get_episode_metadata([0, 400]))
    # Minari's own sampling works on it, and botorl reads back the rows exactly (Minari data only).
    assert len(fast.sample_episodes(5)) == 5
    (tmp_path / "botorl/unit/fast-v0/botorl_flat.npz").unlink()
    back = load_minari("botorl/unit/fast-v0")
    for k in ("observations", "actions", "rewards", "next_observations", "terminals", "episode_ends"):
        np.testing.assert_array_equal(getattr(back, k), getattr(ds, k), err_msg=k)
    np.testing.assert_array_equal(back.infos["success"], ds.infos["success"])


def test_generated_dataset_recovers_its_environment(monkeypatch, tmp_path):
    """Data botorl generates record their env_spec: Minari's recover_environment() makes the
    task's env (offline: the spec points at botorl's own entry point), whose spaces are the data's."""
    import minari

    from botorl.data.generate import cache_id, data_dir, ensure_dataset

    monkeypatch.setenv("BOTORL_DATA_DIR", str(tmp_path))
    ds = ensure_dataset("pointmaze-umaze", 300, 0, progress=False)
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(data_dir()))
    m = minari.load_dataset(cache_id("pointmaze-umaze", 300, 0))
    assert m.spec.env_spec is not None and m.spec.env_spec.id == "botorl/pointmaze-umaze-v0"
    env = m.recover_environment()
    obs, _ = env.reset(seed=0)
    assert obs.shape == (ds.obs_dim,) and env.action_space.shape == (ds.action_dim,)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert "success" in info
    env.close()

"""Loaders read small files the tests write in the real formats; bad input -> clear errors."""

from __future__ import annotations

import pickle

import h5py
import numpy as np
import pytest

from botorl.data import loaders
from botorl.envs.registry import get_task
from botorl.errors import DataFormatError, DatasetNotFoundError


# ----------------------------------------------------------------------------- D4RL


def write_d4rl(path, n=8, timeouts=True, **override):
    obs = np.arange(n * 3, dtype=np.float32).reshape(n, 3)
    data = {
        "observations": obs,
        "actions": np.full((n, 2), 0.5, np.float32),
        "rewards": np.arange(n, dtype=np.float32),
        "terminals": np.zeros(n, bool),
    }
    data["terminals"][2] = True
    if timeouts:
        data["timeouts"] = np.zeros(n, bool)
        data["timeouts"][5] = True
    data.update(override)
    with h5py.File(path, "w") as f:
        for k, v in data.items():
            f.create_dataset(k, data=v)
        f.create_dataset("infos/goal", data=np.zeros((n, 2)))
    return data


def test_d4rl_qlearning_semantics(tmp_path):
    p = tmp_path / "antmaze.hdf5"
    write_d4rl(p, n=8)
    ds = loaders.load_d4rl_hdf5(p)
    # D4RL qlearning_dataset: rows 0..6 (the last has no next obs), row 5 (timeout) dropped.
    kept = [0, 1, 2, 3, 4, 6]
    np.testing.assert_array_equal(ds.rewards, kept)
    np.testing.assert_array_equal(ds.next_observations[:, 0], (np.array(kept) + 1) * 3)
    np.testing.assert_array_equal(ds.terminals, [0, 0, 1, 0, 0, 0])
    # Episodes end at the terminal (2), before the timeout row (4), and at the last row.
    np.testing.assert_array_equal(ds.episode_ends, [0, 0, 1, 0, 1, 1])
    assert ds.metadata["source"] == str(p)


def test_d4rl_without_timeouts_uses_step_counter(tmp_path):
    p = tmp_path / "kitchen.hdf5"
    write_d4rl(p, n=10, timeouts=False, terminals=np.zeros(10, bool))
    ds = loaders.load_d4rl_hdf5(p, max_episode_steps=4)
    # Counter reaches max-1 = 3 at rows 3 and 7: those rows start no transition.
    np.testing.assert_array_equal(ds.rewards, [0, 1, 2, 4, 5, 6, 8])
    np.testing.assert_array_equal(ds.episode_ends, [0, 0, 1, 0, 0, 1, 1])
    whole = loaders.load_d4rl_hdf5(p)
    assert len(whole) == 9 and whole.num_episodes == 1


def test_d4rl_bad_files(tmp_path):
    txt = tmp_path / "fake.hdf5"
    txt.write_text("this is not hdf5")
    with pytest.raises(DataFormatError, match=r"fake\.hdf5.*not a readable HDF5"):
        loaders.load_d4rl_hdf5(txt)
    p = tmp_path / "nokeys.hdf5"
    with h5py.File(p, "w") as f:
        f.create_dataset("observations", data=np.zeros((4, 2)))
    with pytest.raises(DataFormatError, match=r"nokeys\.hdf5.*missing D4RL field.*actions"):
        loaders.load_d4rl_hdf5(p)
    p = tmp_path / "short.hdf5"
    write_d4rl(p, n=8, rewards=np.zeros(7, np.float32))
    with pytest.raises(DataFormatError, match=r"short\.hdf5.*different lengths"):
        loaders.load_d4rl_hdf5(p)
    p = tmp_path / "nan.hdf5"
    obs = np.zeros((8, 3), np.float32)
    obs[3, 1] = np.nan
    write_d4rl(p, n=8, observations=obs)
    with pytest.raises(DataFormatError, match=r"nan\.hdf5.*NaN/inf"):
        loaders.load_d4rl_hdf5(p)
    p = tmp_path / "wide.hdf5"
    write_d4rl(p, n=8, actions=np.full((8, 2), 2.0, np.float32))
    with pytest.raises(DataFormatError, match=r"wide\.hdf5.*outside \[-1, 1\]"):
        loaders.load_d4rl_hdf5(p)
    write_d4rl(tmp_path / "ok.hdf5")
    with pytest.raises(DataFormatError, match="expects 29"):
        loaders.load_d4rl_hdf5(tmp_path / "ok.hdf5", obs_dim=29)
    with pytest.raises(DatasetNotFoundError, match="missing.hdf5"):
        loaders.load_d4rl_hdf5(tmp_path / "missing.hdf5")


# ----------------------------------------------------------------------------- Minari


def write_minari_dict_obs(dataset_id, episodes=3, t=4):
    """A Minari dataset with dict observations, written with Minari's own API."""
    import gymnasium as gym
    import minari
    from minari.data_collector import EpisodeBuffer

    obs_space = gym.spaces.Dict({
        "observation": gym.spaces.Box(-np.inf, np.inf, (3,), np.float64),
        "achieved_goal": gym.spaces.Box(-np.inf, np.inf, (2,), np.float64),
    })
    act_space = gym.spaces.Box(-1, 1, (2,), np.float32)
    bufs = []
    for e in range(episodes):
        base = 100 * e + np.arange(t + 1, dtype=np.float64)
        bufs.append(EpisodeBuffer(
            id=e,
            observations={"observation": np.stack([base] * 3, 1), "achieved_goal": np.stack([-base] * 2, 1)},
            actions=np.full((t, 2), 0.25, np.float32),
            rewards=np.arange(t, dtype=np.float64) + e,
            terminations=np.array([False] * (t - 1) + [e == 0]),
            truncations=np.array([False] * (t - 1) + [e != 0]),
            infos={"success": np.array([0.0] * t + [float(e == 0)])},
        ))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        minari.create_dataset_from_buffers(dataset_id, bufs, action_space=act_space, observation_space=obs_space,
                                           algorithm_name="t", author="t", author_email="t", code_permalink="t",
                                           description="t")


def test_minari_by_id_and_path_dict_obs(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    write_minari_dict_obs("testns/dictobs-v0")
    ds = loaders.load_minari("testns/dictobs-v0")
    assert len(ds) == 12 and ds.num_episodes == 3 and ds.obs_dim == 5
    # Sorted keys: achieved_goal (2) then observation (3).
    np.testing.assert_array_equal(ds.observations[1], [-1, -1, 1, 1, 1])
    np.testing.assert_array_equal(ds.next_observations[3], [-4, -4, 4, 4, 4])
    np.testing.assert_array_equal(ds.terminals.nonzero()[0], [3])
    np.testing.assert_array_equal(ds.episode_ends.nonzero()[0], [3, 7, 11])
    np.testing.assert_array_equal(ds.infos["success"][:4], [0, 0, 0, 1])
    ordered = loaders.load_minari(tmp_path / "testns" / "dictobs-v0", obs_keys=["observation", "achieved_goal"])
    np.testing.assert_array_equal(ordered.observations[1], [1, 1, 1, -1, -1])
    with pytest.raises(DataFormatError, match="nope"):
        loaders.load_minari("testns/dictobs-v0", obs_keys=["nope"])
    with pytest.raises(DataFormatError, match="expects 29"):
        loaders.load_minari("testns/dictobs-v0", obs_dim=29)


def test_minari_missing_gives_download_command(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    with pytest.raises(DatasetNotFoundError) as err:
        loaders.load_minari(get_task("antmaze-large-diverse-v2").dataset_source.ref)
    msg = str(err.value)
    assert "minari download D4RL/antmaze/large-diverse-v1" in msg and str(tmp_path) in msg
    assert "minari download D4RL/kitchen/mixed-v2" in loaders.download_hint("kitchen-mixed-v0")
    assert "Cal-QL" in loaders.download_hint("pen-binary-v0")
    err = loaders.dataset_not_found("antmaze-large-play-v2", ["/x"])
    assert isinstance(err, DatasetNotFoundError) and "D4RL/antmaze/large-play-v1" in str(err) and "/x" in str(err)


def test_minari_broken_folder(tmp_path):
    d = tmp_path / "broken-v0" / "data"
    d.mkdir(parents=True)
    (d / "metadata.json").write_text("{not json")
    (d / "main_data.hdf5").write_text("nope")
    with pytest.raises(DataFormatError, match="not a readable Minari dataset"):
        loaders.load_minari(tmp_path / "broken-v0")


# ----------------------------------------------------------------------------- Cal-QL


def calql_files(tmp_path):
    """An expert file (dict observations, one extra reward) and a BC file ((T,1) rewards)."""
    def traj(rewards, dict_obs):
        t = len(rewards)
        obs = [np.full(4, i, np.float32) for i in range(t)]
        nobs = [np.full(4, i + 1, np.float32) for i in range(t)]
        if dict_obs:
            obs = [{"state_observation": o, "image": None} for o in obs]
            nobs = [{"state_observation": o} for o in nobs]
        return {"observations": obs, "next_observations": nobs, "actions": np.full((t, 3), 0.1, np.float32),
                "rewards": np.asarray(rewards, np.float32), "terminals": np.zeros(t, bool),
                "agent_infos": [{}] * t, "env_infos": [{}] * t}

    e1 = traj([-1, -1, 0, 0, -1], True)
    e1["rewards"] = np.append(e1["rewards"], -1.0)  # rlkit's extra reward entry
    e2 = traj([-1, -1, -1], True)  # never succeeds: dropped
    expert = np.empty(2, dtype=object)
    expert[:] = [e1, e2]
    b1 = traj([-1, 0, -1, 0, -1, -1], False)
    b1["rewards"] = b1["rewards"][:, None]
    b1["terminals"] = b1["terminals"][:, None]
    bc = np.empty(1, dtype=object)
    bc[:] = [b1]
    np.save(tmp_path / "door2_sparse.npy", expert, allow_pickle=True)
    np.save(tmp_path / "door_bc_sparse4.npy", bc, allow_pickle=True)
    return tmp_path / "door2_sparse.npy", tmp_path / "door_bc_sparse4.npy"


def test_calql_adroit_pair(tmp_path):
    expert, bc = calql_files(tmp_path)
    ds = loaders.load_calql_adroit(expert, bc)
    # expert: cut after the last success -> 4 rows; the failing trajectory dropped;
    # bc: cut after index 3 -> 4 rows.
    np.testing.assert_array_equal(ds.rewards, [-1, -1, 0, 0, -1, 0, -1, 0])
    np.testing.assert_array_equal(ds.terminals, ds.rewards == 0)
    np.testing.assert_array_equal(ds.episode_ends.nonzero()[0], [3, 7])
    np.testing.assert_array_equal(ds.observations[:, 0], [0, 1, 2, 3, 0, 1, 2, 3])
    np.testing.assert_array_equal(ds.next_observations[:, 0], [1, 2, 3, 4, 1, 2, 3, 4])
    g = 0.99
    mc = ds.with_mc_returns(g, sparse_negative_reward=-1.0).mc_returns
    np.testing.assert_allclose(mc[:4], [-1 - g, -1, 0, 0], rtol=1e-6)
    auto = loaders.load_path(bc)
    assert len(auto) == 4


def test_calql_bad_files(tmp_path):
    (tmp_path / "x.npy").write_bytes(b"garbage")
    with pytest.raises(DataFormatError, match=r"x\.npy.*cannot be read"):
        loaders.load_calql_adroit(tmp_path / "x.npy")
    np.save(tmp_path / "plain.npy", np.zeros(3))
    with pytest.raises(DataFormatError, match="per-trajectory dicts"):
        loaders.load_calql_adroit(tmp_path / "plain.npy")
    arr = np.empty(1, dtype=object)
    arr[:] = [{"observations": [np.zeros(2)]}]
    np.save(tmp_path / "nokey.npy", arr, allow_pickle=True)
    with pytest.raises(DataFormatError, match="lacks key"):
        loaders.load_calql_adroit(None, tmp_path / "nokey.npy")
    with pytest.raises(DatasetNotFoundError, match="Cal-QL"):
        loaders.load_calql_adroit(None, None)


# ----------------------------------------------------------------------------- DAPG


def test_dapg_pickle_dense_and_binary(tmp_path):
    def demo(angles):
        t = len(angles)
        obs = np.zeros((t, 39), np.float32)
        obs[:, 28] = angles
        return {"observations": obs, "actions": np.zeros((t, 28), np.float32),
                "rewards": np.arange(t, dtype=np.float32), "init_state_dict": {"qpos": np.zeros(30)}}

    demos = [demo([0.0, 0.5, 1.4, 1.5, 1.6]), demo([0.0, 0.1, 0.2])]
    p = tmp_path / "door-v0_demos.pickle"
    p.write_bytes(pickle.dumps(demos))
    dense = loaders.load_dapg_demos(p)
    assert len(dense) == 4 + 2 and dense.num_episodes == 2 and not dense.terminals.any()
    np.testing.assert_array_equal(dense.rewards, [0, 1, 2, 3, 0, 1])
    binary = loaders.load_dapg_demos(p, binary_reward=True)
    # Success of the next obs: the step into angle 1.4 (row 1) is the first; cut there.
    np.testing.assert_array_equal(binary.rewards, [-1, 0])
    np.testing.assert_array_equal(binary.terminals, [0, 1])
    assert binary.num_episodes == 1  # the failing demo is dropped
    kept = loaders.load_dapg_demos(p, binary_reward=True, drop_unsuccessful=False)
    np.testing.assert_array_equal(kept.rewards, [-1, 0, -1, -1])
    bad = tmp_path / "bad.pickle"
    bad.write_bytes(pickle.dumps([{"observations": np.zeros((3, 39))}]))
    with pytest.raises(DataFormatError, match=r"bad\.pickle.*lacks key"):
        loaders.load_dapg_demos(bad)


def test_dapg_real_npz(door_demos_path):
    dense = loaders.load_dapg_demos(door_demos_path, obs_dim=39, action_dim=28)
    assert len(dense) == 6729 - 25 and dense.num_episodes == 25
    binary = loaders.load_dapg_demos(door_demos_path, binary_reward=True)
    # Only 7 of the 25 human demos reach the 1.35 rad success angle (max angles 1.07-1.59).
    with np.load(door_demos_path) as z:
        bounds = np.concatenate([[0], np.cumsum(z["episode_lengths"])])
        opened = sum(z["observations"][s + 1 : e, 28].max() >= 1.35 for s, e in zip(bounds[:-1], bounds[1:]))
    assert opened == 7 and binary.num_episodes == opened
    ends = binary.episode_ends.nonzero()[0]
    np.testing.assert_array_equal(binary.terminals.nonzero()[0], ends)
    assert np.all(binary.rewards[ends] == 0) and np.sum(binary.rewards == 0) == opened
    assert np.all(binary.next_observations[binary.rewards < 0, 28] < 1.35)
    assert np.all(binary.next_observations[ends, 28] >= 1.35)


def test_dapg_npz_bad(tmp_path):
    p = tmp_path / "demos.npz"
    np.savez(p, observations=np.zeros((4, 39)), actions=np.zeros((4, 28)))
    with pytest.raises(DataFormatError, match=r"demos\.npz.*lacks key.*rewards"):
        loaders.load_dapg_demos(p)
    np.savez(p, observations=np.zeros((4, 39)), actions=np.zeros((4, 28)), rewards=np.zeros(4),
             episode_lengths=np.array([3, 3]))
    with pytest.raises(DataFormatError, match="lengths do not fit"):
        loaders.load_dapg_demos(p)
    txt = tmp_path / "text.npz"
    txt.write_text("hello")
    with pytest.raises(DataFormatError, match=r"text\.npz.*not a readable"):
        loaders.load_dapg_demos(txt)

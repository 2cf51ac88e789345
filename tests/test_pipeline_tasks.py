"""Each of the paper's six tasks runs BOTO end to end (smoke: a few steps of every stage).

The offline data are small files this test writes in the real formats -- Minari datasets
(dict observations, Minari's own writer) for antmaze and kitchen under
$MINARI_DATASETS_PATH (a temp dir, conftest.py), Cal-QL's pickled ``.npy`` trajectory
arrays for door/pen-binary -- and are read by the data package's loaders; warm-up,
fine-tuning and evaluation step the real env wrappers.
"""

from __future__ import annotations

import csv
import json
import os
import warnings
from pathlib import Path

import numpy as np
import pytest

from botorl.cli import main as botorl_main
from botorl.envs.registry import get_task


def _write_minari(dataset_id: str, obs_parts: dict[str, int], action_dim: int, reward_fn, episodes=3, t=25, seed=0):
    import gymnasium as gym
    import minari
    from minari.data_collector import EpisodeBuffer

    rng = np.random.default_rng(seed)
    obs_space = gym.spaces.Dict({k: gym.spaces.Box(-np.inf, np.inf, (n,), np.float64) for k, n in obs_parts.items()})
    act_space = gym.spaces.Box(-1, 1, (action_dim,), np.float32)
    bufs = []
    for e in range(episodes):
        rewards = reward_fn(rng, t)
        bufs.append(EpisodeBuffer(
            id=e,
            observations={k: rng.normal(size=(t + 1, n)) for k, n in obs_parts.items()},
            actions=rng.uniform(-1, 1, (t, action_dim)).astype(np.float32),
            rewards=rewards,
            terminations=np.zeros(t, bool),
            truncations=np.array([False] * (t - 1) + [True]),
            infos={"success": np.concatenate([[0.0], (rewards > 0).astype(float)])},
        ))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        minari.create_dataset_from_buffers(dataset_id, bufs, action_space=act_space, observation_space=obs_space,
                                           algorithm_name="test", author="botorl tests", author_email="none",
                                           code_permalink="none", description="small test data")


def _write_calql(folder: Path, expert_name: str, bc_name: str, obs_dim: int, action_dim: int, seed=0):
    """Cal-QL adroit-binary files: expert (dict observations) and BC ((T, 1) rewards)."""
    rng = np.random.default_rng(seed)

    def traj(t, dict_obs):
        obs = rng.normal(size=(t + 1, obs_dim)).astype(np.float32)
        rewards = -np.ones(t, np.float32)
        rewards[t // 2:] = 0.0  # succeeds half way
        o, no = list(obs[:-1]), list(obs[1:])
        if dict_obs:
            o = [{"state_observation": x} for x in o]
            no = [{"state_observation": x} for x in no]
        return {"observations": o, "next_observations": no,
                "actions": rng.uniform(-1, 1, (t, action_dim)).astype(np.float32),
                "rewards": rewards, "terminals": np.zeros(t, bool), "agent_infos": [{}] * t, "env_infos": [{}] * t}

    expert = np.empty(2, dtype=object)
    expert[:] = [traj(20, True), traj(16, True)]
    b = traj(24, False)
    b["rewards"] = b["rewards"][:, None]
    b["terminals"] = b["terminals"][:, None]
    bc = np.empty(1, dtype=object)
    bc[:] = [b]
    folder.mkdir(parents=True, exist_ok=True)
    np.save(folder / expert_name, expert, allow_pickle=True)
    np.save(folder / bc_name, bc, allow_pickle=True)
    return folder


def _data_for(task: str, tmp: Path) -> list[str]:
    spec = get_task(task)
    src = spec.dataset_source
    if src.kind == "minari":
        if spec.domain == "antmaze":
            parts = {"achieved_goal": 2, "observation": 27, "desired_goal": 2}
            reward = lambda rng, t: (np.arange(t) >= t - 3).astype(np.float64)  # noqa: E731
        else:
            parts = {"observation": spec.obs_dim}
            reward = lambda rng, t: np.minimum(np.arange(t) // 6, 4).astype(np.float64)  # noqa: E731
        root = Path(os.environ["MINARI_DATASETS_PATH"])
        if not (root / src.ref / "data").is_dir():
            _write_minari(src.ref, parts, spec.action_dim, reward)
        return []
    expert, bc = src.ref.split(",")
    return ["--data.path", str(_write_calql(tmp / task, expert, bc, spec.obs_dim, spec.action_dim))]


@pytest.mark.parametrize(
    "task",
    # antmaze and kitchen once each in the default suite (each task family compiles its own
    # shapes, ~40-60 s); the other four with -m slow (the Adroit wrapper's door-binary-local run
    # stays: test_door_binary_local_with_demos_option)
    ["antmaze-large-diverse-v2", "kitchen-mixed-v0",
     *(pytest.param(t, marks=pytest.mark.slow)
       for t in ("antmaze-large-play-v2", "kitchen-partial-v0", "door-binary-v0", "pen-binary-v0"))],
)
def test_paper_task_smoke(task, tmp_path):
    extra = _data_for(task, tmp_path)
    out = tmp_path / "run"
    code = botorl_main(["run", "--task", task, "--profile", "smoke", "--no-progress", "--no-tensorboard",
                        "--out", str(out), "--eval.episodes", "1", "--eval.num_envs", "1", *extra])
    assert code == 0
    s = json.loads((out / "summary.json").read_text())
    spec = get_task(task)
    assert s["status"] == "finished" and s["alpha"] == spec.paper.alpha and s["pretrain"] == "calql"
    with open(out / "eval.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    # warm-up evaluations at 0 and 20, fine-tuning's at 30 (after the 30-step warm-up) and 40
    assert [int(r["env_step"]) for r in rows] == [0, 20, 30, 40]
    assert all(0.0 <= float(r["success"]) <= 1.0 for r in rows)
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["boto"]["log_sigma"] == spec.paper.log_sigma
    # the warm-up ran the real env and its rewards went through the task's transform
    with np.load(out / "checkpoints" / "warmup-final" / "warmup.npz") as z:
        obs = z["observations"]
        assert obs.shape == (30, spec.obs_dim)
        raw = (z["rewards"] - spec.reward_bias) / spec.reward_scale
        lo, hi = {"antmaze": (0, 1), "kitchen": (0, 4), "adroit": (-1, 0)}[spec.domain]
        assert raw.min() >= lo - 1e-4 and raw.max() <= hi + 1e-4


def test_door_binary_local_with_demos_option(door_demos_path, tmp_path, monkeypatch):
    """door-binary-local makes its data from the demos given by --demos (BOTORL_DOOR_DEMOS unset)."""
    monkeypatch.delenv("BOTORL_DOOR_DEMOS", raising=False)
    out = tmp_path / "door-local"
    code = botorl_main(["run", "--task", "door-binary-local", "--profile", "smoke", "--no-progress",
                        "--no-tensorboard", "--out", str(out), "--eval.episodes", "1", "--eval.num_envs", "1",
                        "--demos", str(door_demos_path)])
    assert code == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["status"] == "finished" and s["task"] == "door-binary-local" and s["alpha"] == 0.0
    assert json.loads((out / "config.json").read_text())["data"]["demos"] == str(door_demos_path)

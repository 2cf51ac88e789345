"""One-step bandit data for the paper's Figures 2 and 3 (the tasks, their densities and rewards:
botorl/envs/bandit.py): every transition terminal, a constant observation ``zeros(1)``, the
action drawn from the task's data density and its reward R(a).
"""

from __future__ import annotations

import numpy as np

from botorl.data.dataset import Dataset
from botorl.envs.bandit import OBS_DIM, bandit_1d_reward, pinwheel_reward, sample_1d, sample_pinwheel



def _one_step_dataset(actions: np.ndarray, rewards: np.ndarray, task: str, steps: int, seed: int) -> Dataset:
    n = len(actions)
    obs = np.zeros((n, OBS_DIM), np.float32)
    ones = np.ones(n, bool)
    return Dataset(obs, actions, rewards, obs.copy(), ones, ones,
                   metadata={"source": f"generated: {task} (steps={steps}, seed={seed})", "task": task,
                             "generator": "botorl.data.generators.bandit", "steps": int(steps), "seed": int(seed)})


def generate_pinwheel(steps: int, seed: int, progress: bool = True) -> Dataset:
    """``steps`` one-step transitions with pinwheel actions and reward ``pinwheel_reward``."""
    rng = np.random.default_rng(seed)
    acts, arm = sample_pinwheel(rng, steps)
    ds = _one_step_dataset(acts, pinwheel_reward(acts), "bandit-pinwheel", steps, seed)
    ds.infos["arm"] = arm.astype(np.float32)
    return ds


def generate_1d(steps: int, seed: int, progress: bool = True) -> Dataset:
    """``steps`` one-step transitions drawn uniformly from ``bandit_1d_support()``."""
    rng = np.random.default_rng(seed)
    acts = sample_1d(rng, steps)
    return _one_step_dataset(acts, bandit_1d_reward(acts), "bandit-1d", steps, seed)

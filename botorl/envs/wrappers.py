"""The one wrapper shape every botorl task has (docs/CONTRACTS.md, "Tasks"): ``TaskEnv`` gives a
flat float32 observation, actions in [-1, 1]^A, the task's reward / termination and
``info["success"]`` in [0, 1]; domains override ``_observe`` and ``_task_step``.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import sys
import types
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces


def import_robotics(module: str = "gymnasium_robotics") -> types.ModuleType:
    """``module`` (gymnasium_robotics or one of its modules), gymnasium_robotics imported without
    its notice that the Adroit *Dense* rewards changed (botorl uses the binary reward); anything
    else printed still reaches stderr."""
    if "gymnasium_robotics" not in sys.modules:
        buf = io.StringIO()
        with contextlib.redirect_stderr(buf):
            import gymnasium_robotics  # noqa: F401  # lazy: the one import of the package, its notice muted
        text = buf.getvalue()
        if text and "reward functions were updated" not in text:
            sys.stderr.write(text)
    return importlib.import_module(module)


class TaskEnv(gym.Wrapper):
    """Flat float32 observations, [-1, 1] actions and ``info["success"]`` for one task; ``seed``
    seeds the first ``reset`` that names none, so an env made with a seed is reproducible."""

    reward_offset = 0.0

    def __init__(self, env: gym.Env, obs_dim: int, seed: int | None = None):
        super().__init__(env)
        act = env.action_space
        if not isinstance(act, spaces.Box) or not (np.all(act.low == -1.0) and np.all(act.high == 1.0)):
            raise ValueError(f"{type(env.unwrapped).__name__}: expected a [-1, 1] Box action space, got {act}")
        self.action_space = spaces.Box(-1.0, 1.0, shape=act.shape, dtype=np.float32)
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(obs_dim,), dtype=np.float32)
        self._pending_seed = seed
        if seed is not None:
            self.action_space.seed(seed)

    def _observe(self, obs: Any) -> np.ndarray:
        return obs

    def _task_step(self, obs: Any, reward: float, terminated: bool, info: dict) -> tuple[float, bool, float]:
        """Return (reward, terminated, success) for one inner step; by default the inner env's
        ``info["success"]`` ends the episode, rewarded ``success + reward_offset``."""
        success = bool(info.get("success", False))
        return float(success) + self.reward_offset, success, float(success)

    def _reset_options(self) -> dict | None:
        return None

    def _after_reset(self, obs: Any, info: dict) -> Any:
        return obs

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is None:
            seed = self._pending_seed
        self._pending_seed = None
        if options is None:
            options = self._reset_options()
        obs, info = self.env.reset(seed=seed, options=options)
        return self._flat(self._after_reset(obs, info)), {**info, "success": 0.0}

    def step(self, action):
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        obs, reward, terminated, truncated, info = self.env.step(action)
        info = dict(info)
        reward, terminated, success = self._task_step(obs, float(reward), bool(terminated), info)
        info["success"] = float(success)
        return self._flat(obs), float(reward), bool(terminated), bool(truncated), info

    def _flat(self, obs: Any) -> np.ndarray:
        return np.asarray(self._observe(obs), dtype=np.float32).reshape(self.observation_space.shape)

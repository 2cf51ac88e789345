"""One-step bandit envs (``bandit-pinwheel``, ``bandit-1d``) so the registry is uniform.

The observation is a constant (a single 0.0); the action is in [-1, 1]^A (A = 2 for the
pinwheel, 1 for the 1-D bandit); the reward is the bandit's R(a) from
``botorl.data.generators.bandit`` (the data generator's own reward, so data and env agree);
every episode ends after one step (terminated; gamma is irrelevant).
``info["success"]`` = (R(a) - min R) / (max R - min R), R's range estimated once on a grid
over the action box, i.e. how close the action is to the best one.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

DIMS = {"pinwheel": (1, 2), "1d": (1, 1)}


def bandit_dims(kind: str) -> tuple[int, int]:
    """(obs_dim, action_dim) of a bandit."""
    return DIMS[kind]


def reward_function(kind: str):
    """R(a) for a batch of actions (N, A) -> (N,), from the bandit data generator."""
    from botorl.data.generators import bandit

    fn = {"pinwheel": bandit.pinwheel_reward, "1d": bandit.bandit_1d_reward}[kind]
    return lambda a: np.asarray(fn(np.asarray(a, np.float64)), dtype=np.float64).reshape(-1)


class BanditEnv(gym.Env):
    metadata = {"render_modes": []}

    def __init__(self, kind: str, reward_fn=None, seed: int | None = None):
        obs_dim, action_dim = DIMS[kind]
        self.kind = kind
        self.reward_fn = reward_fn or reward_function(kind)
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(obs_dim,), dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(action_dim,), dtype=np.float32)
        grid = np.linspace(-1.0, 1.0, 201 if action_dim == 1 else 101)
        pts = np.stack(np.meshgrid(*[grid] * action_dim, indexing="ij"), -1).reshape(-1, action_dim)
        values = self.reward_fn(pts)
        self._rmin, self._rmax = float(values.min()), float(values.max())
        self._obs = np.zeros(obs_dim, dtype=np.float32)
        self._pending_seed = seed
        if seed is not None:
            self.action_space.seed(seed)

    def reset(self, *, seed=None, options=None):
        if seed is None:
            seed, self._pending_seed = self._pending_seed, None
        super().reset(seed=seed)
        return self._obs.copy(), {"success": 0.0}

    def step(self, action):
        a = np.clip(np.asarray(action, dtype=np.float64).reshape(1, -1), -1.0, 1.0)
        r = float(self.reward_fn(a)[0])
        span = self._rmax - self._rmin
        success = float(np.clip((r - self._rmin) / span, 0.0, 1.0)) if span > 0 else 1.0
        return self._obs.copy(), r, True, False, {"success": success}


def make_bandit(kind: str, seed: int | None = None) -> BanditEnv:
    return BanditEnv(kind, seed=seed)

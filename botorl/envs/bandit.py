"""One-step bandits (``bandit-pinwheel``, ``bandit-1d``): the tasks behind the paper's Figures 2
and 3 (docs/tasks.md). Rewards are a deterministic R(a), so the BOTO fixed point can be computed
exactly (algorithms.md section 4). The pinwheel density (polar: ``rho`` a truncated normal,
on arm k ``theta = 2 pi k / K + twist * rho + Normal(0, std^2)``) is exact in
``pinwheel_density``; its reward ``(k(a) + rho) / K`` gives each arm its own range. The 1-D
bandit's actions are uniform over clusters of points, each cluster with its own reward.
``info["success"]`` = R(a) rescaled to [0, 1] by R's range on a grid over the action box.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

OBS_DIM = 1
ACTION_DIM = {"pinwheel": 2, "1d": 1}

PINWHEEL_ARMS = 5
PINWHEEL_RADIUS_MEAN = 0.55
PINWHEEL_RADIUS_STD = 0.15
PINWHEEL_RADIUS_RANGE = (0.05, 0.98)
PINWHEEL_TWIST = 2.5
PINWHEEL_ANGLE_STD = 0.12

# (centre, reward) per cluster; 7 points spaced 0.03 apart around each centre.
BANDIT_1D_CLUSTERS = ((-0.6, 0.3), (0.0, 1.0), (0.55, 0.6))
BANDIT_1D_POINTS_PER_CLUSTER = 7
BANDIT_1D_SPACING = 0.03


def _radius_distribution():
    """rho ~ Normal(mean, std^2) truncated to ``PINWHEEL_RADIUS_RANGE`` (scipy's frozen truncnorm)."""
    from scipy.stats import truncnorm  # lazy: scipy.stats takes ~0.5 s to import; the registry imports this module

    lo, hi = PINWHEEL_RADIUS_RANGE
    a, b = (lo - PINWHEEL_RADIUS_MEAN) / PINWHEEL_RADIUS_STD, (hi - PINWHEEL_RADIUS_MEAN) / PINWHEEL_RADIUS_STD
    return truncnorm(a, b, loc=PINWHEEL_RADIUS_MEAN, scale=PINWHEEL_RADIUS_STD)


def _arm_angle_pdf(rho: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """(..., K): wrapped-normal density of theta around each arm's centre line at radius rho."""
    base = 2 * np.pi * np.arange(PINWHEEL_ARMS) / PINWHEEL_ARMS
    centre = base + PINWHEEL_TWIST * rho[..., None]
    d = (theta[..., None] - centre + np.pi) % (2 * np.pi) - np.pi  # in [-pi, pi)
    s = PINWHEEL_ANGLE_STD
    # Wrapping terms beyond +-2 pi are below 1e-300 for s = 0.12.
    tot = sum(np.exp(-0.5 * ((d + 2 * np.pi * m) / s) ** 2) for m in (-1, 0, 1))
    return tot / (s * np.sqrt(2 * np.pi))


def _polar(actions) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(actions, np.float64)
    return np.hypot(a[..., 0], a[..., 1]), np.arctan2(a[..., 1], a[..., 0])


def sample_pinwheel(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n actions (n, 2) from the pinwheel density, and their arm indices (n,)."""
    arm = rng.integers(0, PINWHEEL_ARMS, size=n)
    rho = _radius_distribution().rvs(size=n, random_state=rng)
    theta = 2 * np.pi * arm / PINWHEEL_ARMS + PINWHEEL_TWIST * rho + rng.normal(0.0, PINWHEEL_ANGLE_STD, size=n)
    acts = np.stack([rho * np.cos(theta), rho * np.sin(theta)], axis=-1)
    return acts.astype(np.float32), arm


def pinwheel_density(actions: np.ndarray) -> np.ndarray:
    """p_D(a) for actions (..., 2): exact density w.r.t. Lebesgue measure on the plane."""
    rho, theta = _polar(actions)
    polar = _radius_distribution().pdf(rho) * _arm_angle_pdf(rho, theta).mean(axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(rho > 0, polar / np.maximum(rho, 1e-300), 0.0)


def pinwheel_arm(actions: np.ndarray) -> np.ndarray:
    """Index of the arm whose density is largest at each action (..., 2) -> (...)."""
    return np.argmax(_arm_angle_pdf(*_polar(actions)), axis=-1)


def pinwheel_reward(actions: np.ndarray) -> np.ndarray:
    """R(a) = (k(a) + rho) / K: arm k's rewards lie in [k/K, (k+1)/K)."""
    rho = np.clip(_polar(actions)[0], 0.0, 1.0 - 1e-9)
    return ((pinwheel_arm(actions) + rho) / PINWHEEL_ARMS).astype(np.float32)


def bandit_1d_support() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(actions (M, 1), rewards (M,), probabilities (M,)) of the 1-D bandit's data distribution."""
    k = BANDIT_1D_POINTS_PER_CLUSTER
    offs = (np.arange(k) - (k - 1) / 2) * BANDIT_1D_SPACING
    acts = np.concatenate([c + offs for c, _ in BANDIT_1D_CLUSTERS])
    rews = np.concatenate([np.full(k, r) for _, r in BANDIT_1D_CLUSTERS])
    probs = np.full(len(acts), 1.0 / len(acts))
    return acts[:, None].astype(np.float32), rews.astype(np.float32), probs


def bandit_1d_reward(actions: np.ndarray) -> np.ndarray:
    """R(a) of the nearest support point (exact on the support, where Q* needs it): (..., 1) or
    (n,) -> (...)."""
    sup, rew, _ = bandit_1d_support()
    a = np.asarray(actions, np.float64)
    if a.ndim > 1 and a.shape[-1] == 1:
        a = a[..., 0]
    idx = np.argmin(np.abs(a[..., None] - sup[:, 0]), axis=-1)
    return rew[idx]


def sample_1d(rng: np.random.Generator, n: int) -> np.ndarray:
    sup, _, probs = bandit_1d_support()
    return sup[rng.choice(len(sup), size=n, p=probs)]


class BanditEnv(gym.Env):
    metadata = {"render_modes": []}

    def __init__(self, kind: str, seed: int | None = None):
        obs_dim, action_dim = OBS_DIM, ACTION_DIM[kind]
        fn = {"pinwheel": pinwheel_reward, "1d": bandit_1d_reward}[kind]
        # R(a) for a batch of actions (N, A) -> (N,)
        self.reward_fn = lambda a: np.asarray(fn(np.asarray(a, np.float64)), dtype=np.float64).reshape(-1)
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

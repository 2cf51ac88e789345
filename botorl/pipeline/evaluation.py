"""Evaluation: deterministic episodes and the Q statistics that show the estimation bias.

Episodes (as WSRL and Cal-QL evaluate; docs/methods.md, "Evaluation"): ``episodes`` (20)
deterministic episodes, tanh of the mean action (``agent.eval_actions``). The envs are
stepped in lockstep and the policy is called once per step on the whole batch of
observations, so an evaluation costs one jitted call per env step, not one per env step per
episode (a single-row call costs ~140 us here). Finished envs keep their last observation in
the batch (the batch shape, and so the compiled function, never changes) and their actions
are discarded.

Success per episode follows the task's ``success_mode``: "any" = the maximum of
``info["success"]`` over the episode, "last" = its value at the final step.

Q statistics: the mean over the critic ensemble of Q(s, a) on a fixed set of dataset pairs
(``q_data``) and on the same states with uniform random actions (``q_uniform``). They are in
the critic's own (reward-transformed) units. ``q_uniform`` far below ``q_data`` is the
conservatism CQL-style pre-training leaves on out-of-distribution actions; BOTO's alpha moves
it (alpha < 0 raises it, alpha > 0 lowers it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np


@dataclass
class EpisodeStats:
    success: float
    episode_return: float
    length: float
    successes: list[float]


def make_eval_envs(spec, eval_cfg) -> list[Any]:
    """One member's evaluation envs (``eval_cfg.envs_per_member`` of them, the same env seeds
    for every member and run; episodes are seeded by their reset seeds, not by the envs)."""
    return [spec.make_env(seed=10_000 + i, evaluation=True) for i in range(eval_cfg.envs_per_member)]


def run_episodes(
    policy: Callable[[np.ndarray], np.ndarray],
    envs: Sequence[Any],
    *,
    episodes: int,
    success_mode: str,
    seed: int,
    max_steps: int | None = None,
) -> EpisodeStats:
    """Run ``episodes`` episodes on ``envs`` in lockstep rounds of ``len(envs)``."""
    if success_mode not in ("any", "last"):
        raise ValueError(f"success_mode must be 'any' or 'last', not {success_mode!r}")
    n_envs = len(envs)
    successes: list[float] = []
    returns: list[float] = []
    lengths: list[int] = []
    episode_index = 0
    while episode_index < episodes:
        n = min(n_envs, episodes - episode_index)
        obs = []
        for i in range(n_envs):
            # every env is reset (the batch keeps its shape); only the first n count
            o, _ = envs[i].reset(seed=int(seed) + episode_index + i)
            obs.append(np.asarray(o, dtype=np.float32))
        obs = np.stack(obs)
        active = np.zeros(n_envs, dtype=bool)
        active[:n] = True
        ret = np.zeros(n_envs)
        length = np.zeros(n_envs, dtype=np.int64)
        succ_any = np.zeros(n_envs)
        succ_last = np.zeros(n_envs)
        step = 0
        while active.any():
            actions = np.asarray(policy(obs))
            for i in np.flatnonzero(active):
                o, r, terminated, truncated, info = envs[i].step(actions[i])
                s = float(info.get("success", 0.0))
                succ_any[i] = max(succ_any[i], s)
                succ_last[i] = s
                ret[i] += float(r)
                length[i] += 1
                obs[i] = np.asarray(o, dtype=np.float32)
                if terminated or truncated or (max_steps is not None and length[i] >= max_steps):
                    active[i] = False
            step += 1
        per = succ_any if success_mode == "any" else succ_last
        successes += per[:n].tolist()
        returns += ret[:n].tolist()
        lengths += length[:n].tolist()
        episode_index += n
    return EpisodeStats(
        success=float(np.mean(successes)),
        episode_return=float(np.mean(returns)),
        length=float(np.mean(lengths)),
        successes=successes,
    )


class QProbe:
    """A fixed set of dataset (s, a) pairs and uniform actions at the same states."""

    def __init__(self, observations: np.ndarray, actions: np.ndarray, seed: int, size: int = 1000):
        rng = np.random.default_rng(seed)
        n = len(observations)
        idx = rng.choice(n, size=min(size, n), replace=n < size)
        self.observations = np.asarray(observations[idx], dtype=np.float32)
        self.actions = np.asarray(actions[idx], dtype=np.float32)
        self.uniform = rng.uniform(-1.0, 1.0, size=self.actions.shape).astype(np.float32)

    def __call__(self, q_fn: Callable[[np.ndarray, np.ndarray], np.ndarray] | None) -> tuple[float, float]:
        if q_fn is None:
            return float("nan"), float("nan")
        q_data = float(np.mean(np.asarray(q_fn(self.observations, self.actions))))
        q_uniform = float(np.mean(np.asarray(q_fn(self.observations, self.uniform))))
        return q_data, q_uniform

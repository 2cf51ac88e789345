"""Evaluation: deterministic episodes (docs/methods.md, "Evaluation") and the Q statistics
that show the estimation bias.

The envs are stepped in lockstep with one policy call per step on the whole batch (a
single-row call costs ~140 us); finished envs keep their last observation in the batch, so its
shape, and the compiled function, never change. Success per episode follows the task's
``success_mode`` (botorl.envs.metric.episode_success).

Q statistics, in the critic's (reward-transformed) units: the ensemble's mean Q on fixed
dataset pairs (``q_data``) and on the same states with uniform actions (``q_uniform``); the
gap is the conservatism CQL-style pre-training leaves, which BOTO's alpha moves.
"""

from __future__ import annotations

import time
from collections import namedtuple
from typing import Any, Callable, Sequence

import numpy as np

from botorl.configs.members import Streams
from botorl.envs.metric import episode_success
from botorl.envs.metric import of_config as metric_of_config
from botorl.envs.registry import get_task
from botorl.io import atomic_write_json

EpisodeStats = namedtuple("EpisodeStats", "success episode_return length")  # means over a member's episodes


def make_eval_envs(spec, eval_cfg) -> list[Any]:
    """One member's ``eval_cfg.envs_per_member`` evaluation envs (the same for every member and
    run; episodes are seeded by their reset seeds)."""
    return [spec.make_env(seed=Streams.EVAL_ENVS + i, evaluation=True) for i in range(eval_cfg.envs_per_member)]


def run_episodes(policy: Callable[[np.ndarray], np.ndarray], envs: Sequence[Sequence[Any]], *, episodes: int,
                 success_mode: str, seeds: Sequence[int], max_steps: int | None = None) -> list[EpisodeStats]:
    """``episodes`` episodes for every member: member i on its own ``envs[i]`` in lockstep rounds
    (reset seeds ``seeds[i] + episode index``), all members' envs stepped together with one
    ``policy`` call per step on (N, E, O) observations -> (N, E, A). Every env is reset each
    round (the batch keeps its shape); only the first ones count. One ``EpisodeStats`` each."""
    n_mem, n_envs = len(envs), len(envs[0])
    rounds = []  # each round's (success, return, length) of its counted episodes, (N, n) each
    for first in range(0, episodes, n_envs):
        n = min(n_envs, episodes - first)
        obs = np.stack([np.stack([np.asarray(envs[m][i].reset(seed=int(seeds[m]) + first + i)[0], np.float32)
                                  for i in range(n_envs)]) for m in range(n_mem)])
        active = np.zeros((n_mem, n_envs), dtype=bool)
        active[:, :n] = True
        ret, succ = np.zeros((n_mem, n_envs)), np.zeros((n_mem, n_envs))
        length = np.zeros((n_mem, n_envs), dtype=np.int64)
        while active.any():
            actions = np.asarray(policy(obs))
            for m, i in zip(*np.nonzero(active)):
                o, r, terminated, truncated, info = envs[m][i].step(actions[m, i])
                succ[m, i] = episode_success(succ[m, i], info.get("success", 0.0), success_mode)
                ret[m, i] += float(r)
                length[m, i] += 1
                obs[m, i] = np.asarray(o, dtype=np.float32)
                if terminated or truncated or (max_steps is not None and length[m, i] >= max_steps):
                    active[m, i] = False
        rounds.append((succ[:, :n], ret[:, :n], length[:, :n]))
    succ, ret, length = (np.concatenate(x, axis=1) for x in zip(*rounds))
    return [EpisodeStats(success=float(np.mean(succ[m])), episode_return=float(np.mean(ret[m])),
                         length=float(np.mean(length[m]))) for m in range(n_mem)]


def evaluate_command(policy: Callable[[np.ndarray], np.ndarray], cfg, episodes: int, head: dict[str, Any], path,
                     q: Callable[[], dict[str, float]] | None = None) -> dict[str, Any]:
    """``botorl eval``'s ``episodes`` of one policy ((1, E, O) -> (1, E, A)) on its own evaluation
    envs, reset seeds from ``Streams.eval_command`` (not those of the run's evaluations); its
    result (``head``, then the task's metric fields: success only where the task defines it,
    botorl/envs/metric.py; ``q()``: Q statistics) written to ``path``."""
    t0 = time.perf_counter()
    spec, metric = get_task(cfg.task), metric_of_config(cfg)
    envs = make_eval_envs(spec, cfg.eval)
    try:
        stats = run_episodes(policy, [envs], episodes=episodes, success_mode=spec.success_mode,
                             seeds=[Streams.of(cfg).eval_command], max_steps=spec.max_episode_steps)[0]
    finally:
        for e in envs:
            e.close()
    result = {**head, "episodes": episodes}
    if metric.name == "success":
        result["success"] = stats.success
    result["return"] = stats.episode_return
    if metric.name == "score":
        result["score"] = metric.of(stats.success, stats.episode_return)
    result.update(episode_length=stats.length, **(q() if q else {}), seconds=round(time.perf_counter() - t0, 2))
    atomic_write_json(path, result)
    return result


class QProbe:
    """A fixed set of dataset (s, a) pairs and uniform actions at the same states."""

    def __init__(self, observations: np.ndarray, actions: np.ndarray, seed: int, size: int = 1000):
        rng = np.random.default_rng(seed)
        n = len(observations)
        idx = rng.choice(n, size=min(size, n), replace=n < size)
        self.observations = np.asarray(observations[idx], dtype=np.float32)
        self.actions = np.asarray(actions[idx], dtype=np.float32)
        self.uniform = rng.uniform(-1.0, 1.0, size=self.actions.shape).astype(np.float32)

    def __call__(self, q_fn: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> dict[str, float]:
        return {"q_data": float(np.mean(np.asarray(q_fn(self.observations, self.actions)))),
                "q_uniform": float(np.mean(np.asarray(q_fn(self.observations, self.uniform))))}

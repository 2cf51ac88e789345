"""``botorl tasks``: list the tasks and the state of their data; ``botorl tasks check TASK``
steps a task's env through all its wrappers and checks the contract (shapes, action box,
``info["success"]`` in [0, 1], finite rewards), printing steps/s and the success rate of
random actions."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Annotated

import numpy as np
import tyro

from botorl.data.tasks import data_status
from botorl.envs.metric import episode_success
from botorl.envs.registry import TaskSpec, get_task, list_tasks
from botorl.errors import Range, check_ranges


@dataclass
class ListConfig:
    """List every task with its domain, horizon, data source and data status."""

    verbose: bool = False
    """also print how to get missing data"""


@dataclass
class CheckConfig:
    """Step a task's env with random actions through all wrappers and check the contract."""

    task: tyro.conf.Positional[str]
    """task name (see `botorl tasks`)"""
    steps: Annotated[int, Range(1, 10**7)] = 1000
    """number of env steps"""
    seed: Annotated[int, Range(0, 2**31 - 1)] = 0


def list_main(cfg: ListConfig) -> int:
    header = ("task", "domain", "horizon", "data", "status", "")
    rows = [(spec.name, spec.domain, str(spec.max_episode_steps), spec.dataset_source.describe(), *data_status(spec))
            for spec in list_tasks()]
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(5)]
    for r in [header, *rows]:
        print("  ".join(c.ljust(w) for c, w in zip(r[:5], widths)))
        if r is not header and (cfg.verbose or r[4] == "missing"):
            print(f"    {r[5]}")
    return 0


def check_task(spec: TaskSpec, steps: int = 1000, seed: int = 0) -> dict:
    """Run ``steps`` random-action steps; returns the numbers and a list of problems."""
    env = spec.make_env(seed)
    problems: list[str] = []
    if env.observation_space.shape != (spec.obs_dim,):
        problems.append(f"observation space {env.observation_space.shape} != dataset spec ({spec.obs_dim},)")
    if env.action_space.shape != (spec.action_dim,):
        problems.append(f"action space {env.action_space.shape} != dataset spec ({spec.action_dim},)")
    if not (np.all(env.action_space.low == -1) and np.all(env.action_space.high == 1)):
        problems.append(f"action space is not [-1, 1]: {env.action_space}")

    def check_obs(obs, where):
        if obs.shape != (spec.obs_dim,) or obs.dtype != np.float32:
            problems.append(f"{where}: observation {obs.shape} {obs.dtype}, expected ({spec.obs_dim},) float32")
        elif not np.all(np.isfinite(obs)):
            problems.append(f"{where}: non-finite observation")

    obs, info = env.reset(seed=seed)
    check_obs(obs, "reset")
    if not 0.0 <= float(info.get("success", -1)) <= 1.0:
        problems.append("reset: info['success'] missing or outside [0, 1]")
    episodes, ep_success, ep_len, ret = [], 0.0, 0, 0.0  # (success, length, return) of each finished one
    start = time.perf_counter()
    for t in range(steps):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        ep_len += 1
        ret += reward
        s = info.get("success")
        if s is None or not 0.0 <= float(s) <= 1.0:
            problems.append(f"step {t}: info['success'] = {s!r}, expected a value in [0, 1]")
            s = 0.0
        ep_success = episode_success(ep_success, s, spec.success_mode)
        if not np.isfinite(reward):
            problems.append(f"step {t}: non-finite reward {reward}")
        if len(problems) > 10:
            break
        if t < 5 or terminated or truncated:
            check_obs(obs, f"step {t}")
        if terminated or truncated:
            episodes.append((ep_success, ep_len, ret))
            ep_success, ep_len, ret = 0.0, 0, 0.0
            obs, info = env.reset()
    elapsed = time.perf_counter() - start
    env.close()
    successes, lengths, returns = zip(*(episodes or [(ep_success, ep_len, ret)]))  # none finished: the running one
    return {"task": spec.name, "steps": steps, "steps_per_s": steps / max(elapsed, 1e-9), "episodes": len(successes),
            "success_rate": float(np.mean(successes)), "mean_return": float(np.mean(returns)),
            "mean_length": float(np.mean(lengths)), "problems": problems}


def check_main(cfg: CheckConfig) -> int:
    spec = get_task(cfg.task)
    r = check_task(spec, cfg.steps, cfg.seed)
    print(
        f"{r['task']}: {r['steps']} random-action steps, {r['steps_per_s']:.0f} steps/s; "
        f"{r['episodes']} episode(s), success rate {r['success_rate']:.3f} ({spec.success_mode}), "
        f"mean return {r['mean_return']:.2f}, mean length {r['mean_length']:.1f}; "
        f"obs ({spec.obs_dim},) float32, actions [-1, 1]^{spec.action_dim}"
    )
    if r["problems"]:
        print("FAILED:\n  " + "\n  ".join(r["problems"]))
        return 1
    print("ok")
    return 0


def main(argv: list[str]) -> int:
    if argv and argv[0] == "check":
        cfg = tyro.cli(CheckConfig, args=argv[1:], prog="botorl tasks check")
        check_ranges(cfg)
        return check_main(cfg)
    return list_main(tyro.cli(ListConfig, args=argv, prog="botorl tasks"))

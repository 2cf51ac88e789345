"""Your own task in botorl: a 2-d point that has to reach a goal, from logged data to a policy.

    python examples/own_task.py                    # BOTO and WSRL, quick profile (minutes)
    python examples/own_task.py --profile smoke    # every stage for a few steps (the tests)

1. a Gymnasium env defined here (``PointGoal``: Dict observations, actions in [-0.1, 0.1]^2,
   ``info["success"]``, episodes of at most 50 steps);
2. logged data from a noisy scripted controller (``logged_data``), as a dict of arrays;
3. ``botorl.register_task`` and ``botorl.run`` for BOTO and WSRL;
4. ``botorl.load_policy`` driving the env in a plain Gymnasium loop.

The same task runs from the command line (docs/own-task.md): copy this file to ``mytask.py``,
write the data with ``python mytask.py --save logged.npz``, then
``botorl run --env mytask:make_env --data.path logged.npz --env-max-steps 50``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium as gym
import numpy as np
from gymnasium import spaces

GOAL = np.array([0.6, 0.6])
MAX_STEPS = 50
SPEED = 0.1  # the largest move per step: the action bounds are [-0.1, 0.1], not [-1, 1]


class PointGoal(gym.Env):
    """A point in the square [-1, 1]^2 starting near (-0.6, -0.6); each action moves it by up to
    0.1 per axis. Reaching within 0.1 of the goal gives reward 1, success and the episode's end."""

    def __init__(self):
        self.observation_space = spaces.Dict({
            "position": spaces.Box(-1.0, 1.0, (2,), np.float32),
            "goal": spaces.Box(-1.0, 1.0, (2,), np.float32),
        })
        self.action_space = spaces.Box(-SPEED, SPEED, (2,), np.float32)
        self.pos = np.zeros(2)

    def _obs(self):
        return {"position": self.pos.astype(np.float32), "goal": GOAL.astype(np.float32)}

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.pos = -0.6 + self.np_random.uniform(-0.2, 0.2, 2)
        return self._obs(), {"success": 0.0}

    def step(self, action):
        self.pos = np.clip(self.pos + np.clip(action, -SPEED, SPEED), -1.0, 1.0)
        success = bool(np.linalg.norm(self.pos - GOAL) < 0.1)
        return self._obs(), float(success), success, False, {"success": float(success)}


def make_env(seed: int = 0) -> gym.Env:
    """botorl's entry point: a fresh env (botorl seeds its first reset with ``seed``)."""
    return PointGoal()


def logged_data(episodes: int = 200, noise: float = 0.05, seed: int = 0) -> dict:
    """Transitions of a scripted controller (full speed towards the goal) with Gaussian noise on
    its actions, in the env's own units; the observations stay dicts, flattened by botorl."""
    rng = np.random.default_rng(seed)
    env = make_env()
    rows: dict[str, list] = {k: [] for k in ("position", "goal", "next_position", "next_goal", "actions", "rewards",
                                             "terminals", "timeouts")}
    for ep in range(episodes):
        obs, _ = env.reset(seed=seed * 100_000 + ep)
        for t in range(MAX_STEPS):
            a = np.clip(SPEED * np.sign(obs["goal"] - obs["position"]) + rng.normal(0, noise, 2), -SPEED, SPEED)
            nxt, r, terminated, truncated, _ = env.step(a)
            for k in ("position", "goal"):
                rows[k].append(obs[k])
                rows["next_" + k].append(nxt[k])
            rows["actions"].append(a)
            rows["rewards"].append(r)
            rows["terminals"].append(terminated)
            rows["timeouts"].append(not terminated and t == MAX_STEPS - 1)
            obs = nxt
            if terminated:
                break
    a = {k: np.asarray(v) for k, v in rows.items()}
    return {"observations": {"position": a["position"], "goal": a["goal"]},
            "next_observations": {"position": a["next_position"], "goal": a["next_goal"]},
            "actions": a["actions"].astype(np.float32), "rewards": a["rewards"].astype(np.float32),
            "terminals": a["terminals"], "timeouts": a["timeouts"]}


def save(data: dict, path: str | Path) -> None:
    """The data as a .npz for ``botorl run --data.path`` (dict observations as ``observations/<key>``)."""
    flat = {}
    for k, v in data.items():
        if isinstance(v, dict):
            flat.update({f"{k}/{kk}": vv for kk, vv in v.items()})
        else:
            flat[k] = v
    np.savez(path, **flat)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--profile", default="quick", choices=["smoke", "quick", "full"])
    p.add_argument("--out", default="runs/own-task", help="folder for the two run directories")
    p.add_argument("--save", metavar="FILE", help="only write the logged data to FILE (.npz) and stop")
    args = p.parse_args()
    data = logged_data()
    if args.save:
        save(data, args.save)
        print(f"{len(data['rewards'])} transitions -> {args.save}")
        return

    import botorl

    # reward 10 r - 5: every step short of the goal costs 5, so a shorter path is worth more and the
    # critic's Q depends on the action (antmaze's transform). On the raw 0/1 reward the quick
    # profile's fine-tuning lost the goal (success 0.85 -> 0 for BOTO and WSRL alike).
    botorl.register_task("point-goal", make_env, data, max_episode_steps=MAX_STEPS, reward_scale=10.0,
                         reward_bias=-5.0)
    runs = {}
    for method in ("boto", "wsrl"):
        summary = botorl.run(task="point-goal", method=method, profile=args.profile, out=f"{args.out}/{method}",
                             progress=False)
        print(f"{method}: status {summary['status']}, success {summary['success_initial']} -> "
              f"{summary['success_final']}")
        runs[method] = summary["run_dir"]

    # the policy outside botorl: observations as the env gives them, actions in its bounds
    policy = botorl.load_policy(runs["boto"])
    env = make_env()
    successes = []
    for episode in range(10):
        obs, info = env.reset(seed=1_000 + episode)
        for _ in range(MAX_STEPS):
            action = policy(obs)
            assert action.shape == env.action_space.shape and env.action_space.contains(action)
            obs, reward, terminated, truncated, info = env.step(action)
            if terminated or truncated:
                break
        successes.append(info["success"])
    print(f"boto's policy in a plain Gymnasium loop: success {np.mean(successes):.2f} over {len(successes)} episodes")


if __name__ == "__main__":
    main()

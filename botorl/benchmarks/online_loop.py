"""Env steps per second of the whole online loop: act, step, insert, update (UTD 4).

The loop is WSRL's fine-tuning loop as ``botorl.pipeline.stages.finetune`` runs it (that
function needs a whole run context, so its body is mirrored here), one env step at a time: the
agent samples an action for the current observation (one jitted call), the real task env
steps, the transition goes into the real ``ReplayBuffer``, a batch of ``utd * batch`` rows
is sampled and ``agent.update`` does utd critic steps + 1 actor + 1 temperature step.
``online_loop_efficiency`` = (env steps/s of this loop) / (updates/s of the same update
alone, measured in the same run): 1.0 means acting, stepping, inserting and sampling cost
nothing beside the update.
"""

from __future__ import annotations

import time
from typing import Any

import jax
import numpy as np


def make_env(task: str = "antmaze", seed: int = 0) -> tuple[Any, str]:
    """The task env: via the task registry where it is there, else the antmaze wrapper,
    else gymnasium's Hopper-v5 (all real MuJoCo envs)."""
    try:
        from botorl.envs.registry import list_tasks

        for spec in list_tasks():
            if spec.domain == task or spec.name == task:
                return spec.make_env(seed), spec.name
    except Exception:
        pass
    if task == "antmaze":
        try:
            from botorl.envs.antmaze import make_antmaze

            return make_antmaze(seed), "antmaze (botorl.envs.antmaze)"
        except Exception:
            pass
    import gymnasium as gym

    return gym.make("Hopper-v5"), "Hopper-v5"


class OnlineLoop:
    """A running online loop whose ``run(n)`` does n env steps."""

    def __init__(self, agent: Any, env: Any, batch: int, utd: int, seed: int = 0, prefill: int = 2000):
        from botorl.data.replay import ReplayBuffer

        self.agent, self.env = agent, env
        self.batch, self.utd = batch, utd
        obs_dim = int(np.prod(env.observation_space.shape))
        action_dim = int(np.prod(env.action_space.shape))
        self.buffer = ReplayBuffer(max(100_000, prefill * 2), obs_dim, action_dim)
        self.rng = np.random.default_rng(seed)
        self.obs, _ = env.reset(seed=seed)
        # WSRL starts fine-tuning with the warm-up data in the buffer; random actions here.
        for _ in range(prefill):
            a = self.rng.uniform(-1, 1, action_dim).astype(np.float32)
            self._env_step(a)

    def _env_step(self, action: np.ndarray) -> None:
        next_obs, reward, terminated, truncated, _ = self.env.step(action)
        self.buffer.insert(self.obs, action, float(reward), next_obs, float(terminated))
        self.obs = next_obs
        if terminated or truncated:
            self.obs, _ = self.env.reset()

    def run(self, n: int) -> None:
        agent = self.agent
        for _ in range(n):
            action, agent = agent.sample_actions(self.obs)
            self._env_step(np.asarray(action, np.float32))
            # As botorl.pipeline.stages.finetune: u minibatches of B, flattened to u*B rows.
            b = self.buffer.sample(self.rng, self.batch, num_batches=self.utd)
            agent, _ = agent.update({k: v.reshape((-1,) + v.shape[2:]) for k, v in b.items()})
        jax.block_until_ready(agent)
        self.agent = agent


def time_rate(run: Any, min_time: float) -> float:
    """Calls per second of ``run(n)`` (n grows until a block lasts ``min_time``)."""
    n = 1
    while True:
        t0 = time.perf_counter()
        run(n)
        elapsed = time.perf_counter() - t0
        if elapsed >= min_time:
            return n / elapsed
        n = max(n + 1, int(n * min(8.0, 1.3 * min_time / max(elapsed, 1e-6))))

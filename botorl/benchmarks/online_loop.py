"""Env steps per second of the whole online loop: fine-tuning's own body
(``pipeline.online.OnlineState.advance``: act, env step, insert, sample, UTD-4 update) for one
run of WSRL's learner. ``online_loop_efficiency`` = its env steps/s over the update alone's
updates/s in the same run: 1.0 means everything beside the update costs nothing.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from botorl.agents.population import stack
from botorl.configs.methods import get_method
from botorl.configs.schema import OnlineConfig, RunConfig
from botorl.pipeline.stages import Window, online_state


class OnlineLoop:
    """A running fine-tuning loop (a population of one) whose ``run(n)`` does n env steps."""

    def __init__(self, agent: Any, spec: Any, batch: int, utd: int, seed: int = 0, prefill: int = 2000):
        # WSRL's learner: the buffer alone (no offline data), utd x batch rows per update; the
        # loop's real inputs, made as the run makes them
        online = OnlineConfig(steps=10**12, batch_size=batch, utd=utd, buffer_capacity=max(100_000, prefill * 2))
        cfg = RunConfig(seed=seed, online=online)
        self.state = online_state(cfg, [cfg], get_method("wsrl"), spec, None, None)
        self.agents, self.window = stack([agent]), Window(1)
        # WSRL starts fine-tuning with the warm-up data in the buffer; random actions here.
        rng = np.random.default_rng(seed)
        for _ in range(prefill):
            self.state.act(rng.uniform(-1, 1, (1, spec.action_dim)).astype(np.float32))

    def run(self, n: int) -> None:
        for _ in range(n):
            self.agents = self.state.advance(self.agents, self.window)
        self.window.rows.clear()  # the metrics stay on the device: the loop logs none here
        jax.block_until_ready(self.agents)

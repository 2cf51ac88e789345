"""Prototypes of the fast paths the profile (benchmarks/profile_calql.py) measures.

These live here, beside the benchmark, until the owners of the agents and the pipeline
take them over; nothing in the training code uses them yet.

- ``DeviceData`` + ``scan_updates``: the offline data sit on the device once; a jitted
  function samples the batch indices with ``jax.random`` and runs K updates under one
  ``lax.scan``: no numpy sampling, no host-to-device copy and one Python dispatch per K
  updates instead of per update.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp

BATCH_KEYS = ("observations", "actions", "rewards", "next_observations", "dones", "mc_returns")


def device_data(batch_like: dict[str, Any]) -> dict[str, jax.Array]:
    """Whole-dataset arrays (rows first, Batch keys) put on the default device once."""
    return {k: jnp.asarray(batch_like[k], jnp.float32) for k in BATCH_KEYS}


@functools.partial(jax.jit, static_argnames=("num_updates", "batch_size"))
def scan_updates(agent: Any, data: dict[str, jax.Array], key: jax.Array, num_updates: int, batch_size: int):
    """``num_updates`` agent updates, each on a uniform batch drawn on the device.

    Uses the agent's traced ``_update`` (the body of its jitted ``update``), so the
    learning step is the agent's own; only where the batch comes from differs.
    """
    n = data["rewards"].shape[0]

    def body(agent, k):
        idx = jax.random.randint(k, (batch_size,), 0, n)
        batch = jax.tree_util.tree_map(lambda x: x[idx], data)
        return agent._update(batch)

    agent, infos = jax.lax.scan(body, agent, jax.random.split(key, num_updates))
    return agent, jax.tree_util.tree_map(jnp.mean, infos)

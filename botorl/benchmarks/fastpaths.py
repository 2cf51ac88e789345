"""The device-sampled training path, as the profile (benchmarks/profile_calql.py) times it.

- ``device_data`` + ``scan_updates``: the offline data sit on the device once; one jitted
  call samples the batch indices with ``jax.random`` and runs K updates under one
  ``lax.scan``: no numpy sampling, no host-to-device copy, one Python dispatch per K
  updates. The training code has it as ``botorl.agents.common.update_many_on_device``
  (pre-training uses it off the CPU, or with ``--offline.sample_on_device True``); this
  module only adapts the benchmark's whole-dataset batch to it.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from botorl.agents.common import BATCH_KEYS, update_many_on_device


def device_data(batch_like: dict[str, Any]) -> dict[str, jax.Array]:
    """Whole-dataset arrays (rows first, Batch keys) put on the default device once."""
    return {k: jnp.asarray(batch_like[k], jnp.float32) for k in BATCH_KEYS}


def scan_updates(agent: Any, data: dict[str, jax.Array], key: jax.Array, num_updates: int, batch_size: int):
    """``num_updates`` agent updates, each on a uniform batch drawn on the device."""
    return update_many_on_device(agent, data, key, num_updates, batch_size)

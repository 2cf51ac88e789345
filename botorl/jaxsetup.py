"""JAX process settings botorl applies before its first jit: the persistent compilation cache
(XLA takes 2.5-5 s per new function on a 2-core CPU; docs/performance.md) and one CPU device
per usable core, over which a population's updates are split (docs/CONTRACTS.md, "Populations").
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

from botorl.errors import BotorlError, ConfigError

_done = False


def cpu_device_count() -> int:
    """JAX CPU devices for this process: one per core it may run on (its affinity, so a sweep
    worker pinned to 2 of 8 cores gets 2), or ``BOTORL_CPU_DEVICES``."""
    env = os.environ.get("BOTORL_CPU_DEVICES", "").strip()
    if env:
        try:
            n = int(env)
        except ValueError:
            raise ConfigError(f"BOTORL_CPU_DEVICES={env!r}: give a number of CPU devices (1 turns the split off).") from None
        if n < 1:
            raise ConfigError(f"BOTORL_CPU_DEVICES={env!r}: give at least 1 (1 turns the split off).")
        return n
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def setup_jax() -> None:
    """Turn on the persistent compilation cache (``BOTORL_JAX_CACHE``: its folder, or ``off``)
    and one CPU device per usable core; idempotent."""
    global _done
    if _done:
        return
    _done = True
    import jax

    # only possible before the first array: afterwards the backend is fixed and this is skipped
    with contextlib.suppress(AttributeError, RuntimeError, ValueError):
        jax.config.update("jax_num_cpu_devices", cpu_device_count())
    try:  # start the backend now: a platform this machine lacks is exit 2, not a traceback later
        jax.devices()
    except (RuntimeError, AssertionError) as err:  # some JAX versions raise a bare AssertionError
        platforms = os.environ.get("JAX_PLATFORMS") or os.environ.get("JAX_PLATFORM_NAME") or "(not set)"
        raise BotorlError(
            f"JAX cannot start its backend (JAX_PLATFORMS={platforms}): {type(err).__name__}: {str(err) or 'no such device'}. "
            f"Unset JAX_PLATFORMS (or set JAX_PLATFORMS=cpu) to run on the CPU, or install the jax build for this "
            f"machine's accelerator."
        ) from None
    where = os.environ.get("BOTORL_JAX_CACHE", str(Path.home() / ".cache" / "botorl" / "jax"))
    if where.lower() == "off":
        return
    with contextlib.suppress(Exception):  # a read-only home must not stop a run; it only costs compile time
        Path(where).mkdir(parents=True, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", where)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)

"""JAX process settings botorl applies before its first jit.

XLA needs 2.5-5 s to compile each new function on a 2-core CPU (docs/performance.md), which
is most of a short run or test. The persistent compilation cache keeps compiled executables on
disk so a second process with the same shapes skips compilation.

JAX sees one CPU device per core the process may use, so a population's updates can run
on every core (``pipeline/population.py``); a single run uses device 0 as before.
"""

from __future__ import annotations

import os
from pathlib import Path

_done = False


def cpu_device_count() -> int:
    """JAX CPU devices for this process: one per core it may run on (its affinity, so a sweep
    worker pinned to 2 of 8 cores gets 2), or ``BOTORL_CPU_DEVICES``."""
    from botorl.errors import ConfigError

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


def _cpu_devices(jax) -> None:
    # A population's updates are split over the CPU devices, one per core
    # (pipeline/population.py: host_shards); one device runs everything else, as before.
    # Only possible before the first array: afterwards the backend is fixed and this is skipped.
    try:
        jax.config.update("jax_num_cpu_devices", cpu_device_count())
    except (AttributeError, RuntimeError, ValueError):
        pass


def _check_backend(jax) -> None:
    """Start JAX's backend now, so that a platform this machine does not have
    (``JAX_PLATFORMS=cuda`` without a GPU) is exit 2 with a message, not a traceback at the first
    array. JAX raises RuntimeError (or, in some versions, a bare AssertionError) there."""
    try:
        jax.devices()
    except (RuntimeError, AssertionError) as err:
        from botorl.errors import BotorlError

        platforms = os.environ.get("JAX_PLATFORMS") or os.environ.get("JAX_PLATFORM_NAME") or "(not set)"
        raise BotorlError(
            f"JAX cannot start its backend (JAX_PLATFORMS={platforms}): {type(err).__name__}: {str(err) or 'no such device'}. "
            f"Unset JAX_PLATFORMS (or set JAX_PLATFORMS=cpu) to run on the CPU, or install the jax build for this "
            f"machine's accelerator."
        ) from None


def setup_jax() -> None:
    """Turn on the persistent compilation cache and one CPU device per usable core (idempotent).

    ``BOTORL_JAX_CACHE`` names the cache folder (default ``~/.cache/botorl/jax``); set it
    to ``off`` to disable the cache.
    """
    global _done
    if _done:
        return
    _done = True
    import jax

    _cpu_devices(jax)
    _check_backend(jax)
    where = os.environ.get("BOTORL_JAX_CACHE", str(Path.home() / ".cache" / "botorl" / "jax"))
    if where.lower() == "off":
        return

    try:
        Path(where).mkdir(parents=True, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", where)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    except Exception:  # a read-only home must not stop a run; it only costs compile time
        pass

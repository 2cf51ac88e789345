"""JAX process settings botorl applies before its first jit: the persistent compilation cache
(XLA takes 2.5-5 s per new function on a 2-core CPU; docs/performance.md) and one CPU device
per usable core, over which a population's updates are split (docs/CONTRACTS.md, "Populations").
"""

from __future__ import annotations

import contextlib
import functools
import os
from pathlib import Path

from botorl.errors import BotorlError, ConfigError


def usable_cores() -> list[int]:
    """The cores this process may run on: its affinity (every core where the system does not say)."""
    try:
        return sorted(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return list(range(os.cpu_count() or 1))


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
    return len(usable_cores())


@functools.cache
def setup_jax() -> None:
    """Turn on the persistent compilation cache (``BOTORL_JAX_CACHE``: its folder, or ``off``)
    and one CPU device per usable core; idempotent."""
    import jax  # lazy: botorl.api imports this module (through pipeline/policy.py), which must not import JAX

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


# ---------------------------------------------------------------------------- matmul precision
# ``RunConfig.precision`` -> the name ``jax.default_matmul_precision`` takes. "tensorfloat32" is
# JAX's HIGH: TF32 on GPUs that have it (Ampere, Hopper), fp32 elsewhere; bf16 is an algorithm
# preset, because JAX's "bfloat16" (DEFAULT) means TF32 on those GPUs. A dot given its own
# precision keeps it (LayerNorm's row statistics are HIGHEST whatever this says). XLA's CPU
# dots compute fp32 whatever the precision says: on a CPU the three give the same numbers.
MATMUL_PRECISIONS = {"highest": "float32", "tf32": "tensorfloat32", "bf16": "BF16_BF16_F32"}
# the unit roundoff of a matmul's inputs at each precision: 2^-p for a p-bit significand
# (fp32 24 bits, TF32 11, bf16 8); the accumulation is fp32 in all three
MATMUL_ROUNDOFF = {"highest": 2.0**-24, "tf32": 2.0**-11, "bf16": 2.0**-8}


def check_precision(precision: str) -> str:
    if precision not in MATMUL_PRECISIONS:
        raise ConfigError(f"precision {precision!r} is not one of {', '.join(MATMUL_PRECISIONS)}; "
                          f"give --precision highest (fp32 matmuls), tf32 (the default) or bf16.")
    return precision


def matmul_precision(precision: str):
    """A context in which every matmul JAX traces runs at ``precision`` (``highest``, ``tf32``,
    ``bf16``; docs/performance.md, "Precision"). The setting is part of jit's cache key, so a
    function called under two precisions compiles one program for each."""
    import jax  # lazy: as in setup_jax

    return jax.default_matmul_precision(MATMUL_PRECISIONS[check_precision(precision)])


def member_tolerance(precision: str) -> float:
    """Largest |member - alone| accepted between a population member's parameters after one
    update and the same agent's alone (tests/test_gpu.py): 2u (u: ``MATMUL_ROUNDOFF``), never below
    1e-4. The two programs sum in other orders, and a value that differs in its last fp32 bits can
    round to the neighbouring input of the precision's format, a jump of up to 2u that the next
    layers carry: highest 1e-4, tf32 9.8e-4 (an H100 measured 2.0e-4), bf16 7.8e-3."""
    return max(1e-4, 2.0 * MATMUL_ROUNDOFF[check_precision(precision)])

"""JAX process settings botorl applies before its first jit.

XLA needs 2.5-5 s to compile each new function on a 2-core CPU (performance.md), which is
most of a short run or test. The persistent compilation cache keeps compiled executables on
disk so a second process with the same shapes skips compilation.
"""

from __future__ import annotations

import os
from pathlib import Path

_done = False


def setup_jax() -> None:
    """Turn on the persistent compilation cache (idempotent).

    ``BOTORL_JAX_CACHE`` names the cache folder (default ``~/.cache/botorl/jax``); set it
    to ``off`` to disable the cache.
    """
    global _done
    if _done:
        return
    _done = True
    where = os.environ.get("BOTORL_JAX_CACHE", str(Path.home() / ".cache" / "botorl" / "jax"))
    if where.lower() == "off":
        return
    import jax

    try:
        Path(where).mkdir(parents=True, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", where)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    except Exception:  # a read-only home must not stop a run; it only costs compile time
        pass

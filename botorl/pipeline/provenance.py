"""What a run was made with, so a result can be traced and two runs compared honestly:

- ``environment_record()``: botorl's commit (when it runs from a git checkout), the versions of
  the packages that decide its numbers, the CPU model and flags, the XLA/JAX settings of the
  environment and the backend; written into ``config.json`` as ``environment`` when a run starts.
- ``pretrain_sha256(run)``: the SHA-256 of the pre-trained agent a run starts from (its
  ``checkpoints/pretrain-final/agent.ckpt``), in ``summary.json``; ``botorl report`` pairs runs by
  it, so two runs are paired only when they start from the very same bytes. The same settings on
  another machine give another pre-training (floating-point order differs by CPU), which a
  config fingerprint cannot tell.

These are integrity records, not authenticity: anyone can write any value into a file.
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import subprocess
from importlib import metadata
from pathlib import Path

from botorl.io import file_sha256
from botorl.pipeline.checkpoint import file_limit

PACKAGES = ("botorl", "jax", "jaxlib", "flax", "optax", "numpy", "mujoco", "gymnasium")
ENV_PREFIXES = ("XLA_", "JAX_", "BOTORL_CPU")  # settings of the environment that change numbers
PRETRAIN_AGENT = Path("pretrain-final") / "agent.ckpt"


def package_version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def botorl_commit() -> str | None:
    """botorl's git commit (``+dirty`` when tracked files differ), or None outside a checkout."""
    root = Path(__file__).resolve().parents[2]
    if not (root / ".git").exists():
        return None
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return f"{head}+dirty" if dirty else head


def _cpu() -> dict[str, str | None]:
    info: dict[str, str] = {}  # the first value of each key: the first core's
    with contextlib.suppress(OSError), open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
        for line in f:
            key, _, value = line.partition(":")
            info.setdefault(key.strip(), value.strip())
    return {"model": info.get("model name") or platform.processor() or None,
            "flags": info.get("flags", info.get("Features")),  # x86's name, ARM's
            "machine": platform.machine(), "cores": os.cpu_count()}


def environment_record() -> dict:
    """The record ``config.json`` keeps under ``environment`` (see the module docstring)."""
    import jax  # lazy: botorl.api imports this module (through pipeline/export.py's package_version)

    devices = jax.devices()
    return {
        "commit": botorl_commit(),
        "python": platform.python_version(),
        "versions": {name: package_version(name) for name in PACKAGES},
        "cpu": _cpu(),
        "backend": jax.default_backend(),
        "device": devices[0].device_kind if devices else None,
        "device_count": len(devices),
        "env": {k: v for k, v in sorted(os.environ.items()) if k.startswith(ENV_PREFIXES)},
    }


def comparable(record: dict) -> str:
    """The part of an environment record that can change a run's numbers (not the commit's
    dirtiness alone, not the core count), as one string for grouping."""
    if not isinstance(record, dict):
        return "unknown"
    cpu = record.get("cpu") if isinstance(record.get("cpu"), dict) else {}
    keep = {"commit": str(record.get("commit") or "").removesuffix("+dirty"), "versions": record.get("versions"),
            "cpu": {k: cpu.get(k) for k in ("model", "flags")}, "backend": record.get("backend"),
            "device": record.get("device"), "env": record.get("env")}
    return json.dumps(keep, sort_keys=True, default=str)


_CACHE: dict[tuple, str] = {}


def pretrain_sha256(checkpoints: Path) -> str | None:
    """The digest of the pre-trained agent under a run's ``checkpoints`` folder (None: none yet,
    or a method without pre-training); cached by size and mtime, as summaries are written often."""
    path = Path(checkpoints) / PRETRAIN_AGENT
    try:
        st = os.stat(path)
    except OSError:
        return None
    if not os.path.isfile(path):
        return None
    key = (str(path), st.st_size, st.st_mtime_ns)
    if key not in _CACHE:
        try:
            _CACHE[key] = file_sha256(path, file_limit())
        except ValueError:  # more than this machine holds: no agent of botorl's, so no digest to pair runs by
            return None
    return _CACHE[key]

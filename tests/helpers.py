"""Helpers shared by the tests (imported as ``from helpers import ...``); the fixtures are in
conftest.py, which pytest loads first (it sets the environment these run in)."""

from __future__ import annotations

import builtins
import os
from pathlib import Path
from typing import Sequence

import numpy as np

from botorl.data.dataset import BATCH_KEYS
from botorl.data.replay import split_counts
from botorl.errors import BotorlError

REPO_ROOT = Path(__file__).resolve().parents[1]


def load_example(name: str):
    """``examples/<name>.py`` imported as a module (the examples are scripts, not a package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"{name}_example", REPO_ROOT / "examples" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def subprocess_env() -> dict[str, str]:
    """The environment of a botorl subprocess: this checkout first on the path."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO_ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def sigkill_in_finetune(cmd: list[str], out: Path, *, cwd=None, timeout: float = 600):
    """Start ``cmd`` (a `botorl run`), SIGKILL it as soon as ``out`` holds a mid-fine-tuning
    checkpoint, and return (the step it was killed at, the process). Fails the test when no
    such checkpoint appears; latest.json must never be read half-written (atomic writes)."""
    import json
    import signal
    import subprocess
    import time

    proc = subprocess.Popen(cmd, cwd=cwd, env=subprocess_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)
    latest = out / "checkpoints" / "latest.json"
    killed_at = None
    deadline = time.time() + timeout
    try:
        while time.time() < deadline and proc.poll() is None:
            if latest.exists():
                try:
                    info = json.loads(latest.read_text())
                except json.JSONDecodeError:
                    raise AssertionError("latest.json was read half-written") from None
                if info["stage"] == "finetune" and not info["stage_done"]:
                    os.kill(proc.pid, signal.SIGKILL)
                    killed_at = info["step"]
                    break
            time.sleep(0.02)
    finally:
        if proc.poll() is None and killed_at is None:
            os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    assert killed_at is not None, f"no mid-stage checkpoint appeared; stderr: {proc.stderr.read().decode()[-2000:]}"
    return killed_at, proc


# ------------------------------------------------------------------ reference samplers for the replay tests


class FinishedRows:
    """The rows of a single ``ReplayBuffer`` whose episode has ended, oldest first (a live view):
    the reference for ``ReplayBuffer.sample_members(..., finished=True)``."""

    def __init__(self, buffer):
        self.buffer = buffer

    def __len__(self) -> int:
        return self.buffer.finished_len()

    def batch_at(self, idx: np.ndarray) -> dict:
        b = self.buffer
        oldest = b.insert_index if b.size == b.capacity else 0
        return b.batch_at((oldest + np.asarray(idx)) % b.capacity)

    def sample(self, rng: np.random.Generator, batch_size: int, num_batches: int | None = None) -> dict:
        if len(self) == 0:
            raise BotorlError("no finished episode in the replay buffer yet; wait for one to end before sampling.")
        shape = (batch_size,) if num_batches is None else (num_batches, batch_size)
        return self.batch_at(rng.integers(0, len(self), size=shape))


def sample_mixed(
    sources,
    ratios: Sequence[float],
    rng: np.random.Generator,
    batch_size: int,
    num_batches: int | None = None,
) -> dict:
    """One Batch whose rows come from ``sources`` in proportion ``ratios``: the reference for
    ``ReplayBuffer.sample_members(..., offline=...)``.

    Rows are grouped by source in the order given (source 0's rows first); each source is
    sampled uniformly with replacement. An empty source's share goes to the non-empty ones
    (in proportion to their ratios), so RLPD-style mixing works before the first online
    step; if all are empty this raises. With ``num_batches=K`` the result is (K, B, ...).
    """
    if len(sources) != len(ratios):
        raise ValueError(f"{len(sources)} sources but {len(ratios)} ratios")
    ratios = [float(r) if len(s) > 0 else 0.0 for s, r in zip(sources, ratios)]
    if sum(ratios) <= 0:
        raise BotorlError("sample_mixed: every source with a positive ratio is empty; nothing to sample.")
    counts = split_counts(ratios, batch_size)
    parts = []
    for src, c in zip(sources, counts):
        if c == 0:
            continue
        shape = (c,) if num_batches is None else (num_batches, c)
        parts.append(src.batch_at(rng.integers(0, len(src), size=shape)))
    axis = 0 if num_batches is None else 1
    return {k: np.concatenate([p[k] for p in parts], axis=axis) for k in BATCH_KEYS}


def as_minibatches(batch: dict, utd: int, axis: int = 0) -> dict:
    """``batch`` with its rows (at ``axis``) split into ``utd`` critic minibatches, (B, ...) ->
    (utd, B / utd, ...): one SAC update at UTD ``utd``, laid out as the online loop passes it."""
    return {k: v.reshape(v.shape[:axis] + (utd, v.shape[axis] // utd) + v.shape[axis + 1:]) for k, v in batch.items()}


class Payload:
    """A crafted pickle's object: unpickling it creates ``marker`` (a stand-in for any shell command);
    the hostile-input tests show botorl never does."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (builtins.open, (self.marker, "w"))

"""Fault injection for the reliability tests (tests/test_reliability_*.py); no effect unless asked.

* ``BOTORL_KILL_AT=STAGE:STEP``: SIGKILL when STAGE first reaches STEP, after all that step
  does (its checkpoint included);
* ``BOTORL_KILL_IN_CHECKPOINT=NAME:PHASE``: SIGKILL inside the writer of checkpoint NAME, PHASE
  ``files`` (the agent file written into the temporary folder, the rest not yet) or
  ``renamed`` (the folder in place, ``latest.json`` not yet pointing at it);
* ``BOTORL_PAUSE_AT=STAGE:STEP`` with ``BOTORL_PAUSE_FILE=PATH``: there, create PATH and wait
  while it exists (at most 10 minutes), so a test can send a real signal;
* ``set_hook(fn)`` in-process: ``fn(kind, stage_or_name, step_or_phase)`` at the same points
  (a test copies the run directory there: what a kill -9 would leave).
"""

from __future__ import annotations

import os
import signal
import time
from typing import Callable

_hook: Callable[[str, str, object], None] | None = None
_kill_at: tuple[str, int] | None = None
_kill_ckpt: tuple[str, str] | None = None
_pause_at: tuple[str, int, str] | None = None


def _read_env() -> None:
    global _kill_at, _kill_ckpt, _pause_at
    if at := os.environ.get("BOTORL_KILL_AT"):
        stage, _, step = at.rpartition(":")
        _kill_at = (stage, int(step))
    if ck := os.environ.get("BOTORL_KILL_IN_CHECKPOINT"):
        name, _, phase = ck.rpartition(":")
        if phase not in ("files", "renamed"):
            raise ValueError(f"BOTORL_KILL_IN_CHECKPOINT: phase must be files or renamed, not {phase!r}")
        _kill_ckpt = (name, phase)
    if pause := os.environ.get("BOTORL_PAUSE_AT"):
        stage, _, step = pause.rpartition(":")
        _pause_at = (stage, int(step), os.environ["BOTORL_PAUSE_FILE"])


def set_hook(fn: Callable[[str, str, object], None] | None) -> None:
    """In-process callback at every step end and checkpoint phase (None: off)."""
    global _hook
    _hook = fn


def step(stage: str, step_: int) -> None:
    """Called by the stages at the end of each step (or chunk of steps)."""
    global _pause_at
    if _hook is not None:
        _hook("step", stage, int(step_))
    if _kill_at is not None and _kill_at[0] == stage and step_ >= _kill_at[1]:
        os.kill(os.getpid(), signal.SIGKILL)
    if _pause_at is not None and _pause_at[0] == stage and step_ >= _pause_at[1]:
        path, _pause_at = _pause_at[2], None  # once
        with open(path, "w") as f:
            f.write(str(os.getpid()))
        deadline = time.monotonic() + 600
        while os.path.exists(path) and time.monotonic() < deadline:
            time.sleep(0.01)


def checkpoint(name: str, phase: str) -> None:
    """Called by the checkpoint writer at its phases (``files``, ``renamed``)."""
    if _hook is not None:
        _hook("checkpoint", name, phase)
    if _kill_ckpt == (name, phase):
        os.kill(os.getpid(), signal.SIGKILL)


_read_env()

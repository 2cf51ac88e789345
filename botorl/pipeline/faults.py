"""Fault injection for the reliability tests; no effect unless asked.

The tests kill a run at chosen points and check that ``botorl resume`` ends where an
uninterrupted run ends (tests/test_reliability_resume.py). Two ways to ask:

* environment variables, for a real ``botorl run`` subprocess, which then SIGKILLs itself:
  ``BOTORL_KILL_AT=STAGE:STEP`` -- when STAGE (pretrain, warmup, boto, finetune) first reaches
  STEP, after everything that step does (its checkpoint included);
  ``BOTORL_KILL_IN_CHECKPOINT=NAME:PHASE`` -- inside the writer of checkpoint NAME (e.g.
  ``finetune-step000000040``): PHASE ``files`` after the agent file is written into the
  temporary folder (the rest not yet), ``renamed`` after the folder is renamed into place but
  before ``latest.json`` points at it.
* ``BOTORL_PAUSE_AT=STAGE:STEP`` with ``BOTORL_PAUSE_FILE=PATH``: when STAGE first reaches
  STEP the run creates PATH and waits while it exists (at most 10 minutes), so a test can
  send a real signal while a chosen stage runs (tests/test_reliability_preempt.py).
* ``set_hook(fn)`` in-process: ``fn(kind, stage_or_name, step_or_phase)`` is called at the same
  points (``kind`` "step" or "checkpoint"); a test copies the run directory there, which is
  what a kill -9 at that point leaves on disk (every write before it is complete).

The checks cost one ``is None`` test per step when nothing is asked.
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
_active = False


def _read_env() -> None:
    global _kill_at, _kill_ckpt, _pause_at, _active
    at = os.environ.get("BOTORL_KILL_AT")
    if at:
        stage, _, step = at.rpartition(":")
        _kill_at = (stage, int(step))
    ck = os.environ.get("BOTORL_KILL_IN_CHECKPOINT")
    if ck:
        name, _, phase = ck.rpartition(":")
        if phase not in ("files", "renamed"):
            raise ValueError(f"BOTORL_KILL_IN_CHECKPOINT: phase must be files or renamed, not {phase!r}")
        _kill_ckpt = (name, phase)
    pause = os.environ.get("BOTORL_PAUSE_AT")
    if pause:
        stage, _, step = pause.rpartition(":")
        _pause_at = (stage, int(step), os.environ["BOTORL_PAUSE_FILE"])
    _active = _hook is not None or _kill_at is not None or _kill_ckpt is not None or _pause_at is not None


def set_hook(fn: Callable[[str, str, object], None] | None) -> None:
    """In-process callback at every step end and checkpoint phase (None: off)."""
    global _hook
    _hook = fn
    _read_env()


def _die() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def step(stage: str, step_: int) -> None:
    """Called by the stages at the end of each step (or chunk of steps)."""
    if not _active:
        return
    if _hook is not None:
        _hook("step", stage, int(step_))
    if _kill_at is not None and _kill_at[0] == stage and step_ >= _kill_at[1]:
        _die()
    if _pause_at is not None and _pause_at[0] == stage and step_ >= _pause_at[1]:
        _pause(_pause_at[2])


def _pause(path: str) -> None:
    global _pause_at
    _pause_at = None  # once
    with open(path, "w") as f:
        f.write(str(os.getpid()))
    deadline = time.monotonic() + 600
    while os.path.exists(path) and time.monotonic() < deadline:
        time.sleep(0.01)


def checkpoint(name: str, phase: str) -> None:
    """Called by the checkpoint writer at its phases (``files``, ``renamed``)."""
    if not _active:
        return
    if _hook is not None:
        _hook("checkpoint", name, phase)
    if _kill_ckpt is not None and _kill_ckpt == (name, phase):
        _die()


_read_env()

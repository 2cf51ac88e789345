"""SIGTERM and SIGINT: stop at the next step boundary with a checkpoint there, exit 143 / 130
(docs/reliability.md, "Preemption").

The commands that train install ``handling()``. A first signal outside training raises
``Interrupted`` at once; inside ``deferred()`` (the stage loop) it only sets the flag the
stages read at their step boundaries (``stages.stage_loop``). A second signal exits at once;
copies within ``DUPLICATE_S`` of the first count as the first (SLURM signals every process of
a job, and a sweep forwards it to its trial). Without ``handling()`` the flag is never set.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time

from botorl.errors import Interrupted

DUPLICATE_S = 1.0
SIGNALS = (signal.SIGTERM, signal.SIGINT)

_requested: int | None = None  # the first signal's number
_first_at = 0.0
_deferring = 0
_installed = False


def requested() -> int | None:
    """The signal that asked the run to stop, or None."""
    return _requested


def interrupted() -> Interrupted:
    """The exception a stage raises once it has saved its checkpoint."""
    return Interrupted(_requested or signal.SIGINT)


def _handler(signum: int, frame) -> None:
    global _requested, _first_at
    now = time.monotonic()
    if _requested is not None:
        if now - _first_at < DUPLICATE_S:
            return  # the same preemption, delivered twice (scheduler and sweep)
        print(f"\nbotorl: {signal.Signals(signum).name} again: exiting now; the last complete checkpoint is "
              f"kept (`botorl resume DIR` continues from it).", file=sys.stderr, flush=True)
        os._exit(128 + signum)
    _requested, _first_at = signum, now
    if _deferring:
        print(f"\nbotorl: {signal.Signals(signum).name}: stopping at the next step with a checkpoint (a second "
              f"signal exits at once).", file=sys.stderr, flush=True)
        return
    raise Interrupted(signum)


@contextlib.contextmanager
def handling():
    """Install the handlers for SIGTERM and SIGINT (main thread only; elsewhere: no-op)."""
    global _installed, _requested
    if _installed or threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {s: signal.signal(s, _handler) for s in SIGNALS}
    _installed, _requested = True, None
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        _installed = False


@contextlib.contextmanager
def deferred():
    """Inside: a first signal only sets the flag the stages check (see the module docstring)."""
    global _deferring
    _deferring += 1
    try:
        if _requested is not None and _deferring == 1:
            raise Interrupted(_requested)  # arrived just before: nothing has started yet
        yield
    finally:
        _deferring -= 1


@contextlib.contextmanager
def resumable(how: str):
    """An ``Interrupted`` raised inside says ``how`` to continue, unless it says so already."""
    try:
        yield
    except Interrupted as err:
        err.how = err.how or how
        raise

"""The run directory: every file a run writes (the layout: docs/running.md, "The run
directory"; docs/CONTRACTS.md "Runs"), and ``DIR/.lock`` (``RunLock``).

Whole files are written atomically (botorl/io.py); the CSV/JSONL logs are appended line by
line and on resume cut back to the checkpoint's step (``truncate``), so no row appears twice.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import fcntl
import io
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable

from botorl.errors import BotorlError, ConfigError
from botorl.io import (IO_FAULTS, UnsafeFileError, append_text, atomic_write_bytes, jsonable, open_regular,
                       read_bounded, read_bounded_bytes)
from botorl.io import read_json_bounded as read_json  # what every reader of a run's JSON files calls

LOCK_FILE = ".lock"
POPULATION_FILE = "population.json"  # what makes a directory a population's (botorl/pipeline/cli.py)
LOG_LIMIT = 1 << 30  # a metrics or eval log botorl reads back (on resume, for the summary)

EVAL_COLUMNS = ["stage", "env_step", "success", "return", "q_data", "q_uniform"]


class RunDir:
    """Paths of one run directory."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        self.config = self.root / "config.json"
        self.eval_csv = self.root / "eval.csv"
        self.metrics = self.root / "metrics"
        self.checkpoints = self.root / "checkpoints"
        self.summary = self.root / "summary.json"
        self.curve = self.root / "curve.png"
        self.tb = self.root / "tb"

    def create(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        for sub in (self.metrics, self.checkpoints, self.tb):
            # a folder replaced by a link would take the run's writes outside its directory
            if sub.is_symlink():
                raise UnsafeFileError(f"{sub} is a symbolic link; botorl writes a run's files only inside its "
                                      f"directory. Remove the link (or give another --out) and run the command again.")
        self.metrics.mkdir(exist_ok=True)
        self.checkpoints.mkdir(exist_ok=True)


def check_out(out: Path) -> None:
    """ConfigError (exit 2) unless ``--out`` can be a run directory: not an existing file, not
    inside the kernel's pseudo file systems (/proc, /sys, /dev)."""
    resolved = Path(os.path.realpath(out))
    if resolved.parts[1:2] and resolved.parts[1] in ("proc", "sys", "dev"):
        raise ConfigError(f"--out {out} is inside /{resolved.parts[1]}, the kernel's view of the machine, not a place "
                          f"for files; give a folder on a disk, e.g. --out runs/my-run.")
    first = next((p for p in (out, *out.parents) if p.exists()), None)  # the nearest part that exists
    if first is not None and not first.is_dir():
        where = "is an existing file" if first == out else f"is inside {first}, an existing file"
        raise ConfigError(f"--out {out} {where}, not a folder; give a new folder (or an existing one) for the run.")


# ----------------------------------------------------------------------------- ownership
class RunIOError(BotorlError):
    """The run directory cannot be written (disk full, read-only, no permission)."""


@contextlib.contextmanager
def io_guard(where):
    """An OSError inside that is a full / read-only / forbidden output becomes ``RunIOError`` (exit 2)."""
    try:
        yield
    except OSError as err:
        if err.errno not in IO_FAULTS:
            raise
        detail = f" ({err.filename})" if err.filename else ""
        raise RunIOError(
            f"cannot write to {where}{detail}: {IO_FAULTS[err.errno]} ({err.strerror}). Free space or pick a "
            f"writable --out; the run's checkpoints so far are kept, and `botorl resume {where}` continues it."
        ) from None


class RunLockedError(BotorlError):
    """Another live process owns the run directory."""


class RunLock:
    """One owner per run directory: an exclusive ``flock`` on ``DIR/.lock``, which holds the PID;
    a second live process gets ``RunLockedError`` (exit 2). The kernel drops a flock when its
    process dies (kill -9 too), so a killed run's lock is taken over; the file is never deleted
    (that would let two processes lock two different files). A sweep's lock is one too:
    ``name`` its file, ``stamp`` what it holds instead of the PID, ``busy(holder)`` its error."""

    def __init__(self, root: str | os.PathLike, name: str = LOCK_FILE, stamp: str | None = None,
                 busy: Callable[[str], BotorlError] | None = None):
        self.root = Path(root)
        self.path = self.root / name
        self.stamp = stamp
        self.busy = busy
        self._fd: int | None = None

    def holder(self) -> str:
        try:
            return read_bounded(self.path, 256).strip() or "unknown"
        except (OSError, ValueError):
            return "unknown"

    def acquire(self) -> "RunLock":
        if self._fd is not None:
            return self
        self.root.mkdir(parents=True, exist_ok=True)
        fd = open_regular(self.path, os.O_RDWR | os.O_CREAT, 0o644)  # never through a link
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            os.close(fd)
            if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                if self.busy is not None:
                    raise self.busy(self.holder()) from None
                raise RunLockedError(
                    f"{self.root} is in use by another botorl process (PID {self.holder()}, lock file "
                    f"{self.path}). Wait for it to finish or stop it, or give another --out."
                ) from None
            raise
        os.ftruncate(fd, 0)
        os.pwrite(fd, (self.stamp or f"{os.getpid()}\n").encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is None:
            return
        try:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
        finally:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> "RunLock":
        with io_guard(self.root):
            return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


# ----------------------------------------------------------------------------- line logs
def log_lines(path: Path, *, warn: bool = False) -> list[str]:
    """The complete UTF-8 lines of an append-only log (a last line cut by a kill and undecodable
    lines left out, with ``warn`` saying so), so a damaged tail never makes a run unresumable."""
    if not path.exists() and not path.is_symlink():
        return []
    try:
        data = read_bounded_bytes(path, LOG_LIMIT)
    except ValueError as err:  # a link, a FIFO, a device, a huge file
        raise UnsafeFileError(f"{path} cannot be read as a botorl log: {err}. Remove it (or give another --out) and "
                              f"run the command again.") from None
    lines = data.split(b"\n")
    torn = lines.pop()  # what follows the last newline: empty unless the last line was cut
    out = []
    for b in lines:
        with contextlib.suppress(UnicodeDecodeError):
            out.append(b.decode("utf-8"))
    bad = len(lines) - len(out)
    if warn and (torn or bad):
        what = [f"{bad} line(s) that are not UTF-8 text"] if bad else []
        what += ["a last line cut short"] if torn else []
        _warn(f"{path}: {' and '.join(what)} left out; the log goes on from its last complete record.")
    return out


class CsvLog:
    """Append-only CSV with a fixed header (the first row's keys; later extra keys dropped)."""

    def __init__(self, path: Path, columns: list[str] | None = None):
        self.path = Path(path)
        header = next(csv.reader(log_lines(self.path)[:1]), None)  # an existing log keeps its own columns
        self.columns = header or (list(columns) if columns else None)

    def append(self, row: dict[str, Any]) -> None:
        new = not self.path.exists() or self.path.stat().st_size == 0
        if self.columns is None:
            self.columns = list(row.keys())
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=self.columns, extrasaction="ignore", lineterminator="\n")
        if new:
            w.writeheader()
        w.writerow({k: _fmt(row.get(k, "")) for k in self.columns})
        append_text(self.path, buf.getvalue())

    def rows(self, *, warn: bool = False) -> list[dict[str, str]]:
        return [r for r in csv.DictReader(log_lines(self.path, warn=warn)) if r]

    def truncate(self, keep) -> None:
        """Keep only rows for which ``keep(row)`` is true (atomic rewrite)."""
        if not self.path.exists():
            return
        rows = self.rows(warn=True)
        buf = io.StringIO()
        cols = self.columns or (list(rows[0].keys()) if rows else [])
        w = csv.DictWriter(buf, fieldnames=cols, extrasaction="ignore", lineterminator="\n")
        w.writeheader()
        w.writerows(r for r in rows if keep(r))
        atomic_write_bytes(self.path, buf.getvalue().encode())


def _fmt(v: Any) -> Any:
    v = _scalar(v)
    return f"{v:.6g}" if isinstance(v, float) else v


class JsonlLog:
    def __init__(self, path: Path):
        self.path = Path(path)

    def append(self, row: dict[str, Any]) -> None:
        append_text(self.path, json.dumps(jsonable(row)) + "\n")

    def truncate(self, keep) -> None:
        if not self.path.exists():
            return
        out = []
        for line in log_lines(self.path, warn=True):
            with contextlib.suppress(ValueError, RecursionError):  # an empty line, one cut by a kill, or not botorl's
                row = json.loads(line)
                if keep(row):
                    out.append(json.dumps(row))
        atomic_write_bytes(self.path, ("\n".join(out) + ("\n" if out else "")).encode())


def _warn(msg: str) -> None:
    print(f"botorl: warning: {msg}", file=sys.stderr)


class TBWriter:
    """TensorBoard scalars written in the caller's thread (tensorboardX's ``EventsWriter``).

    ``SummaryWriter``'s background thread dies on ENOSPC / EROFS and its full queue then blocks
    the run forever; here the first I/O error turns TensorBoard off with one warning instead.
    Non-finite values are skipped (TensorBoard rejects them).
    """

    def __init__(self, logdir: Path, flush_secs: float = 30.0):
        from tensorboardX.event_file_writer import EventsWriter  # lazy: optional dependency (the tensorboard extra)

        self.logdir = Path(logdir)
        self.flush_secs = flush_secs
        self._writer = None
        self._next_flush = time.monotonic() + flush_secs
        try:
            self.logdir.mkdir(parents=True, exist_ok=True)
            self._writer = EventsWriter(str(self.logdir / "events"))
        except OSError as err:
            self._disable(err)

    @property
    def enabled(self) -> bool:
        return self._writer is not None

    def _disable(self, err: BaseException) -> None:
        _warn(f"TensorBoard logging to {self.logdir} turned off ({type(err).__name__}: {err}); "
              "the CSV/JSONL logs in metrics/ go on.")
        w, self._writer = self._writer, None
        if w is not None:
            with contextlib.suppress(Exception):
                w.close()

    def add_scalar(self, tag: str, value: Any, step: int) -> None:
        v = number(value)
        if self._writer is None or not math.isfinite(v):  # not a number, or one TensorBoard rejects
            return
        try:
            # lazy: optional dependency (the tensorboard extra), as in __init__
            from tensorboardX.proto.event_pb2 import Event
            from tensorboardX.summary import scalar

            self._writer.write_event(Event(wall_time=time.time(), step=int(step), summary=scalar(tag, v)))
            if time.monotonic() >= self._next_flush:
                self._next_flush = time.monotonic() + self.flush_secs
                self._writer.flush()
        except OSError as err:
            self._disable(err)

    def close(self) -> None:
        if self._writer is not None:
            w, self._writer = self._writer, None
            try:
                w.close()
            except OSError as err:
                _warn(f"TensorBoard events in {self.logdir} could not be closed ({err}).")


class MetricsLogger:
    """metrics/<stage>.csv + .jsonl, and TensorBoard / W&B when available / asked."""

    def __init__(self, run: RunDir, *, tensorboard: bool = True, wandb_run: Any = None):
        self.run = run
        self._by_stage: dict[str, tuple[CsvLog, JsonlLog]] = {}
        self._tb: TBWriter | None = None
        self._wandb = wandb_run
        if tensorboard:
            with contextlib.suppress(ImportError):  # tensorboardX is optional
                self._tb = TBWriter(run.tb)

    def _wandb_log(self, data: dict[str, Any]) -> None:
        # W&B talks to its own service process; a failure there must not stop the run.
        try:
            self._wandb.log(data)
        except Exception as err:
            _warn(f"W&B logging turned off ({type(err).__name__}: {err}).")
            self._wandb = None

    def _logs(self, stage: str) -> tuple[CsvLog, JsonlLog]:
        if stage not in self._by_stage:
            self._by_stage[stage] = CsvLog(self.run.metrics / f"{stage}.csv"), JsonlLog(self.run.metrics / f"{stage}.jsonl")
        return self._by_stage[stage]

    def log(self, stage: str, step: int, metrics: dict[str, Any]) -> None:
        row = {"step": int(step)} | {k: _scalar(v) for k, v in metrics.items()}
        for log in self._logs(stage):
            log.append(row)
        if self._tb is not None:
            for k, v in row.items():
                if k != "step" and isinstance(v, (int, float)):
                    self._tb.add_scalar(f"{stage}/{k}", v, step)
        if self._wandb is not None:
            # rows of the online stages also carry env_step, their W&B x-axis (pipeline/tracking.py)
            self._wandb_log({f"{stage}/{k}": v for k, v in row.items() if k != "step"} | {f"{stage}/step": step}
                            | ({"env_step": step} if stage in ("warmup", "finetune") else {}))

    def log_eval(self, row: dict[str, Any]) -> None:
        if self._tb is not None:
            for k in ("success", "return", "q_data", "q_uniform"):
                self._tb.add_scalar(f"eval/{k}", row.get(k), row["env_step"])
        if self._wandb is not None:
            self._wandb_log({f"eval/{k}": row[k] for k in ("success", "return", "q_data", "q_uniform")}
                            | {"eval/env_step": row["env_step"], "env_step": row["env_step"]})

    def truncate(self, stage: str, max_step: int) -> None:
        """Drop rows of ``stage`` logged after ``max_step`` (they are redone after a resume)."""
        for log in self._logs(stage):
            log.truncate(lambda r: number(r.get("step")) <= max_step)

    def close(self) -> None:
        if self._tb is not None:
            self._tb.close()
            self._tb = None


def _scalar(v: Any) -> Any:
    if hasattr(v, "item") and callable(v.item):
        try:
            return v.item()
        except (ValueError, TypeError):
            return float("nan")
    return v


def number(v: Any) -> float:
    """A log row's value as a number; inf for what is none (a row cut by a kill comes after every step)."""
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.inf


class MemberRun:
    """One member of a population: its own config (seed, alpha), run directory and logs."""

    def __init__(self, cfg, run: RunDir, wandb_run=None, error: str | None = None):
        self.cfg = cfg
        self.run = run
        run.create()
        self.logger = MetricsLogger(run, tensorboard=cfg.tensorboard, wandb_run=wandb_run)
        self.eval_log = CsvLog(run.eval_csv, EVAL_COLUMNS)
        self.q_log = CsvLog(run.metrics / "q_probe.csv", ["stage", "step", "q_data", "q_uniform"])
        self.error = error  # set when this member diverged (the others go on)

    def truncate_logs(self, order: tuple[str, ...], mid: dict | None, done: list[str]) -> None:
        """Forget a member's log rows written after the checkpoint a resume starts from."""
        def kept(stage: str) -> int:  # the last step of a stage's logs that stays: its mid-stage checkpoint's
            return int(mid["step"]) if (mid is not None and mid["stage"] == stage) else -1

        for stage in order:
            if stage not in done:
                self.logger.truncate(stage, kept(stage))
        if "finetune" not in done:
            # evaluations of finished stages (the warm-up's) stay; fine-tuning's up to its checkpoint
            self.eval_log.truncate(lambda r: r.get("stage") in done or number(r.get("env_step")) <= kept("finetune"))
        self.q_log.truncate(lambda r: r.get("stage") in done)

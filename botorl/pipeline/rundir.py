"""The run directory: every file a run writes (the layout: docs/running.md, "The run
directory"; docs/CONTRACTS.md "Runs"), and ``DIR/.lock`` (``RunLock``).

Whole files are written atomically (botorl/io.py); the CSV/JSONL logs are appended line by
line and on resume cut back to the checkpoint's step (``truncate``), so no row appears twice.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import math
import os
import socket
import struct
import time
from pathlib import Path
from typing import Any, Callable

from botorl.errors import BotorlError, ConfigError
from botorl.errors import warn as _warn  # the log readers name their flag `warn`
from botorl.io import (IO_FAULTS, UnsafeFileError, append_text, atomic_write_bytes, check_path_text, csv_rows,
                       csv_text, jsonable, open_regular, own_folder, read_bounded, read_bounded_bytes, unshare)
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
        # a folder replaced by a link would take the run's writes outside its directory
        own_folder(self.root, self.tb, make=False)
        own_folder(self.root, self.metrics)
        own_folder(self.root, self.checkpoints)


def check_out(out: str | Path, flag: str = "--out") -> Path:
    """``out`` as a Path, or ConfigError (exit 2) unless the text given for ``flag`` can be an
    output folder (a run's, a sweep's, a report's): a path Linux can open (``check_path_text``),
    not an existing file, not inside the kernel's pseudo file systems (/proc, /sys, /dev)."""
    check_path_text(flag, str(out))
    out = Path(out)
    resolved = Path(os.path.realpath(out))
    if resolved.parts[1:2] and resolved.parts[1] in ("proc", "sys", "dev"):
        raise ConfigError(f"{flag} {out} is inside /{resolved.parts[1]}, the kernel's view of the machine, not a place "
                          f"for files; give a folder on a disk, e.g. {flag} runs/my-run.")
    first = next((p for p in (out, *out.parents) if p.exists()), None)  # the nearest part that exists
    if first is not None and not first.is_dir():
        where = "is an existing file" if first == out else f"is inside {first}, an existing file"
        raise ConfigError(f"{flag} {out} {where}, not a folder; give a new folder (or an existing one).")
    return out


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
        fd = open_regular(self.path, os.O_RDWR | os.O_CREAT, 0o644, root=self.root, shared=True)  # never through a link
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
        if os.fstat(fd).st_nlink > 1:
            # a hard link (a `cp -al` snapshot's lock is the original run's; or a file outside):
            # replaced, under its flock, by a file of its own, locked before the rename, so its
            # other names keep their bytes and no second owner gets in between
            try:
                fd = unshare(self.path, fd, prepare=lambda new: fcntl.flock(new, fcntl.LOCK_EX | fcntl.LOCK_NB))
            except BaseException:
                os.close(fd)
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

    def __init__(self, path: Path, columns: list[str] | None = None, *, root: Path | None = None):
        self.path = Path(path)
        self.root = root  # the run directory: no folder between it and the log is a link (io.own_folder)
        header = self._read(log_lines(self.path)[:1])[0]  # an existing log keeps its own columns
        self.columns = header or (list(columns) if columns else None)

    def _read(self, lines: list[str]):
        try:
            return csv_rows(lines, str(self.path))
        except ValueError as err:  # a field over the csv module's limit, a NUL byte
            raise UnsafeFileError(f"{err}. Remove the file (or give another --out) and run the command again.") from None

    def append(self, row: dict[str, Any]) -> None:
        new = not self.path.exists() or self.path.stat().st_size == 0
        if self.columns is None:
            self.columns = list(row.keys())
        text = csv_text(self.columns if new else None, [[_fmt(row.get(k, "")) for k in self.columns]])
        append_text(self.path, text, root=self.root)

    def rows(self, *, warn: bool = False) -> list[dict[str, str]]:
        return [r for r in self._read(log_lines(self.path, warn=warn))[1] if r]

    def truncate(self, keep) -> None:
        """Keep only rows for which ``keep(row)`` is true (atomic rewrite)."""
        if not self.path.exists():
            return
        rows = self.rows(warn=True)
        cols = self.columns or (list(rows[0].keys()) if rows else [])
        text = csv_text(cols, ([r.get(k, "") for k in cols] for r in rows if keep(r)))
        atomic_write_bytes(self.path, text.encode(), root=self.root)


def _fmt(v: Any) -> Any:
    v = _scalar(v)
    return f"{v:.6g}" if isinstance(v, float) else v


class JsonlLog:
    def __init__(self, path: Path, *, root: Path | None = None):
        self.path = Path(path)
        self.root = root  # as CsvLog's

    def append(self, row: dict[str, Any]) -> None:
        append_text(self.path, json.dumps(jsonable(row)) + "\n", root=self.root)

    def truncate(self, keep) -> None:
        if not self.path.exists():
            return
        out = []
        for line in log_lines(self.path, warn=True):
            with contextlib.suppress(ValueError, RecursionError):  # an empty line, one cut by a kill, or not botorl's
                row = json.loads(line)
                if keep(row):
                    out.append(json.dumps(row))
        atomic_write_bytes(self.path, ("\n".join(out) + ("\n" if out else "")).encode(), root=self.root)


class TBWriter:
    """TensorBoard scalars written in the caller's thread, into an events file botorl makes new
    (``O_EXCL``: a name already there, a link's included, is never opened, so nothing outside the
    run is written), records in TFRecord framing (the record's length, its masked CRC-32C, the
    record, its masked CRC-32C; tensorboardX's protos and checksum).

    ``SummaryWriter``'s background thread dies on ENOSPC / EROFS and its full queue then blocks
    the run forever; here the first I/O error turns TensorBoard off with one warning instead.
    Non-finite values are skipped (TensorBoard rejects them). ``root``: the run directory
    (``io.own_folder``).
    """

    def __init__(self, logdir: Path, flush_secs: float = 30.0, root: Path | None = None):
        # lazy: optional dependency (the tensorboard extra); ImportError: off
        from tensorboardX.proto.event_pb2 import Event

        self.logdir = Path(logdir)
        self.flush_secs = flush_secs
        self._file = None
        self._next_flush = time.monotonic() + flush_secs
        try:
            own_folder(root if root is not None else self.logdir, self.logdir)
            self._file = os.fdopen(self._new_file(root), "wb")
            self._write(Event(wall_time=time.time(), file_version="brain.Event:2"))
        except OSError as err:
            self._disable(err)

    def _new_file(self, root: Path | None) -> int:
        name = f"events.out.tfevents.{int(time.time()):010d}.{socket.gethostname()}"
        for k in range(100):  # a name taken (another process this second, a planted file): the next
            with contextlib.suppress(FileExistsError):
                return open_regular(self.logdir / (f"{name}.{k}" if k else name), os.O_WRONLY | os.O_CREAT | os.O_EXCL,
                                    root=root)
        raise FileExistsError(errno.EEXIST, "no free events file name", str(self.logdir / name))

    @property
    def enabled(self) -> bool:
        return self._file is not None

    def _write(self, event) -> None:
        from tensorboardX.record_writer import masked_crc32c  # lazy: as in __init__

        data = event.SerializeToString()
        header = struct.pack("Q", len(data))
        crc = struct.pack("I", masked_crc32c(header)), struct.pack("I", masked_crc32c(data))
        self._file.write(header + crc[0] + data + crc[1])

    def _sync(self) -> None:
        self._file.flush()
        os.fsync(self._file.fileno())

    def _close(self) -> None:
        """Synced and closed; TensorBoard is off from here on, whatever the close raises."""
        try:
            self._sync()
        finally:
            f, self._file = self._file, None
            f.close()

    def _disable(self, err: BaseException) -> None:
        _warn(f"TensorBoard logging to {self.logdir} turned off ({type(err).__name__}: {err}); "
              "the CSV/JSONL logs in metrics/ go on.")
        if self._file is not None:
            with contextlib.suppress(Exception):
                self._close()

    def add_scalar(self, tag: str, value: Any, step: int) -> None:
        v = number(value)
        if self._file is None or not math.isfinite(v):  # not a number, or one TensorBoard rejects
            return
        try:
            # lazy: optional dependency (the tensorboard extra), as in __init__
            from tensorboardX.proto.event_pb2 import Event
            from tensorboardX.summary import scalar

            self._write(Event(wall_time=time.time(), step=int(step), summary=scalar(tag, v)))
            if time.monotonic() >= self._next_flush:
                self._next_flush = time.monotonic() + self.flush_secs
                self._sync()
        except OSError as err:
            self._disable(err)

    def close(self) -> None:
        if self._file is not None:
            try:
                self._close()
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
                self._tb = TBWriter(run.tb, root=run.root)

    def _wandb_log(self, data: dict[str, Any]) -> None:
        # W&B talks to its own service process; a failure there must not stop the run.
        try:
            self._wandb.log(data)
        except Exception as err:
            _warn(f"W&B logging turned off ({type(err).__name__}: {err}).")
            self._wandb = None

    def _logs(self, stage: str) -> tuple[CsvLog, JsonlLog]:
        if stage not in self._by_stage:
            self._by_stage[stage] = (CsvLog(self.run.metrics / f"{stage}.csv", root=self.run.root),
                                     JsonlLog(self.run.metrics / f"{stage}.jsonl", root=self.run.root))
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
        self.eval_log = CsvLog(run.eval_csv, EVAL_COLUMNS, root=run.root)
        self.q_log = CsvLog(run.metrics / "q_probe.csv", ["stage", "step", "q_data", "q_uniform"], root=run.root)
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

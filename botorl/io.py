"""Atomic file writes (a temporary file in the same folder, fsync-ed, then ``os.replace``), so
a process killed at any moment leaves the old file or the new one; and bounded, link-safe
reads of the files in a run directory. Written files get the umask's mode, not mkstemp's 0600,
so run directories stay readable by a shared group.
"""

from __future__ import annotations

import csv
import errno
import hashlib
import io
import json
import math
import os
import stat
import sys
import tempfile
from pathlib import Path
from typing import Any, Iterable

from botorl.errors import BotorlError, ConfigError

_UMASK = os.umask(0)
os.umask(_UMASK)  # reading the umask needs setting it; restored at once


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_UMASK)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        try:
            os.replace(tmp, path)
        except IsADirectoryError:  # a folder where botorl keeps a file: the user's to remove
            raise _not_regular(path, "a directory") from None
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write_bytes(path, text.encode())


def jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if hasattr(x, "item") and callable(x.item):  # numpy / jax scalars
        try:
            x = x.item()
        except (ValueError, TypeError):
            return str(x)
    if isinstance(x, float) and not math.isfinite(x):
        return None if math.isnan(x) else (1e308 if x > 0 else -1e308)
    if isinstance(x, (str, int, float, bool)) or x is None:
        return x
    return str(x)


def atomic_write_json(path: str | os.PathLike, obj: Any, *, indent: int | None = 2, exact: bool = False) -> Path:
    """JSON with numpy scalars unwrapped and non-finite floats made valid JSON (NaN -> null);
    ``exact``: ``obj`` as Python's json writes it (NaN / Infinity kept, to be read back exactly)."""
    return atomic_write_text(path, json.dumps(obj if exact else jsonable(obj), indent=indent) + "\n")


# OSErrors that say the machine cannot take the output (not a bug in botorl): exit 2 with a
# message naming the place, never a traceback.
IO_FAULTS = {errno.ENOSPC: "the disk is full", errno.EDQUOT: "the disk quota is exceeded",
             errno.EROFS: "the file system is read-only", errno.EACCES: "permission denied",
             errno.EPERM: "operation not permitted"}


def pyplot():
    """matplotlib's pyplot drawing to files only (figures are made on machines without a display)."""
    # lazy: matplotlib only where a figure is drawn, and its backend chosen before pyplot loads
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: after the backend is chosen (above)

    return plt


def atomic_save_figure(fig: Any, path: str | os.PathLike, **savefig_kwargs: Any) -> Path:
    """``fig.savefig`` written atomically; the format comes from ``path``'s suffix."""
    out = io.BytesIO()
    fig.savefig(out, format=Path(path).suffix.lstrip(".") or None, **savefig_kwargs)
    return atomic_write_bytes(path, out.getvalue())


def pid_alive(pid: int) -> bool:
    """Whether a process with this id exists (one of another user's counts as alive)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def file_sha256(path: str | os.PathLike, limit: int) -> str:
    """The SHA-256 of the file ``path``, sized first: ValueError naming its size and ``limit``
    when it holds more (a 1 TB sparse file is refused at once, not read for minutes)."""
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        if size > limit:
            raise ValueError(f"{Path(path).name} is {size:,} bytes, more than the {limit:,} botorl reads of such a file")
        return hashlib.file_digest(f, "sha256").hexdigest()


# ---------------------------------------------------------------------------------------------
# Files inside a run, population or sweep directory. Such a directory is data from anywhere (a
# colleague's archive, a shared disk): a file in it may be a symbolic link to something outside,
# a FIFO that blocks whoever opens it, a device or a huge file. Readers take only regular files
# of a bounded size; appenders and locks open without following a link.

JSON_LIMIT = 16 << 20  # config.json, summary.json, population.json, a checkpoint's state.json, ...
SWEEP_JSON_LIMIT = 64 << 20  # sweep.json: a grid of thousands of trials, each with its log tail
CSV_LIMIT = 64 << 20


class UnsafeFileError(BotorlError):
    """A file botorl writes in a run directory is a symbolic link or not a regular file."""


def _not_regular(path: Path, what: str) -> UnsafeFileError:
    return UnsafeFileError(
        f"{path} is {what}, not a regular file. botorl writes only regular files inside a run, population or "
        f"sweep directory (a link there could make it write anywhere); remove it and run the command again."
    )


def open_regular(path: str | os.PathLike, flags: int, mode: int = 0o644) -> int:
    """``os.open`` of a regular file that follows no symbolic link and never blocks on a FIFO
    (``O_NONBLOCK``: a FIFO or device is opened, seen and closed); ``UnsafeFileError`` (exit 2)
    otherwise."""
    path = Path(path)
    try:
        fd = os.open(path, flags | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, mode)
    except OSError as err:
        if err.errno == errno.ELOOP:
            raise _not_regular(path, "a symbolic link") from None
        if err.errno == errno.ENXIO:  # a FIFO without a reader, opened for writing
            raise _not_regular(path, "a FIFO") from None
        if err.errno == errno.EISDIR:  # a folder, opened for writing (a lock file, a log)
            raise _not_regular(path, "a directory") from None
        raise
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode):
        os.close(fd)
        raise _not_regular(path, "a directory" if stat.S_ISDIR(st.st_mode) else "a special file")
    return fd


def append_text(path: str | os.PathLike, text: str) -> None:
    """Append ``text`` to the regular file ``path`` (created if missing), following no link."""
    fd = open_regular(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666 & ~_UMASK)
    with os.fdopen(fd, "w", newline="") as f:
        f.write(text)
        f.flush()


def read_bounded_bytes(path: str | os.PathLike, limit: int, *, tail: bool = False) -> bytes:
    """The bytes of a regular file of at most ``limit`` bytes (``tail``: its last ``limit``
    bytes, whatever its size); ValueError or OSError saying what is wrong otherwise."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as err:
        if err.errno == errno.ELOOP:
            raise ValueError(f"{path.name} is a symbolic link, not a regular file") from None
        raise
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise ValueError(f"{path.name} is not a regular file")
        if st.st_size > limit and not tail:
            raise ValueError(f"{path.name} is {st.st_size:,} bytes, more than the {limit:,} a run's file may hold")
        if tail and st.st_size > limit:
            os.lseek(fd, st.st_size - limit, os.SEEK_SET)
        chunks, left = [], limit
        while left > 0:
            b = os.read(fd, min(left, 1 << 20))
            if not b:
                break
            chunks.append(b)
            left -= len(b)
    finally:
        os.close(fd)
    return b"".join(chunks)


def read_bounded(path: str | os.PathLike, limit: int, *, tail: bool = False) -> str:
    """``read_bounded_bytes`` as UTF-8 text (``tail``: undecodable bytes replaced); ValueError
    (not a regular file, too large, not UTF-8) or OSError otherwise."""
    path = Path(path)
    data = read_bounded_bytes(path, limit, tail=tail)
    try:
        return data.decode("utf-8", errors="replace" if tail else "strict")
    except UnicodeDecodeError as err:
        raise ValueError(f"{path.name} is not UTF-8 text ({err.reason} at byte {err.start})") from None


def _finite_float(text: str) -> float:
    v = float(text)
    if math.isinf(v):  # 1e400: no number botorl writes (it writes Infinity, or "inf", as such)
        raise ValueError(f"the number {text[:40]} is beyond a float")
    return v


def _float_sized_int(text: str) -> int:
    v = int(text)
    if abs(v) > sys.float_info.max:  # 10**400: would overflow wherever it meets a float
        raise ValueError(f"the number {text[:40]}... is beyond a float")
    return v


def read_json_bounded(path: str | os.PathLike, limit: int = JSON_LIMIT) -> Any:
    """The JSON document in the regular file ``path`` (at most ``limit`` bytes); ValueError
    (not a regular file, too large, not UTF-8, not JSON, nested too deep, a number beyond a
    float) or OSError."""
    text = read_bounded(path, limit)
    try:
        return json.loads(text, parse_float=_finite_float, parse_int=_float_sized_int)
    except RecursionError:
        raise ValueError(f"{Path(path).name} is nested too deeply to be a botorl file") from None


# Bytes of an output folder's path: Linux opens paths under 4,096 bytes (PATH_MAX), names of at most
# 255 (NAME_MAX); 512 are left for what botorl makes inside (a sweep's trial, a checkpoint's files).
MAX_PATH = 4096 - 512


def check_path_text(flag: str, path: str) -> None:
    """ConfigError unless ``path`` (the text given for ``flag``) names a folder Linux can open with
    botorl's files inside: not empty (which would mean the working directory), at most
    ``MAX_PATH`` bytes, 255 a name."""
    if not str(path).strip():
        raise ConfigError(f"{flag} is empty; give a folder, e.g. {flag} runs/my-run.")
    raw = os.fsencode(str(path))
    if len(raw) > MAX_PATH or any(len(part) > 255 for part in raw.split(b"/")):
        raise ConfigError(f"{flag} {str(path)[:60]}... is {len(raw):,} bytes long; give a path of at most {MAX_PATH:,} "
                          f"bytes whose names are at most 255 bytes each.")


def csv_rows(lines: Iterable[str], name: str) -> tuple[list[str] | None, list[dict[str, str]]]:
    """(header, rows) of CSV text; ValueError naming the file for what the csv module refuses (a
    field over its size limit, a NUL byte), so a reader's ``except ValueError`` covers a bad CSV."""
    try:
        reader = csv.DictReader(lines)
        return reader.fieldnames, list(reader)
    except csv.Error as err:
        raise ValueError(f"{name} is not CSV botorl wrote ({err})") from None


def read_json_object(path: str | os.PathLike, limit: int = JSON_LIMIT) -> dict[str, Any] | None:
    """The JSON object in ``path`` (a regular file of at most ``limit`` bytes), else None: for
    files botorl may find missing, cut short or not its own (a sweep's, a run's being written)."""
    try:
        data = read_json_bounded(path, limit)
        return data if isinstance(data, dict) else None
    except (OSError, ValueError):
        return None

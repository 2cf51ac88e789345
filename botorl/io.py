"""Atomic file writes (a temporary file in the same folder, fsync-ed, then ``os.replace``), so
a process killed at any moment leaves the old file or the new one; and bounded, link-safe
reads of the files in a run directory. Written files get the umask's mode, not mkstemp's 0600,
so run directories stay readable by a shared group.
"""

from __future__ import annotations

import contextlib
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
from typing import Any, Callable, Iterable, Sequence

from botorl.errors import BotorlError, ConfigError

_UMASK = os.umask(0)
os.umask(_UMASK)  # reading the umask needs setting it; restored at once


def atomic_write_bytes(path: str | os.PathLike, data: bytes, *, root: str | os.PathLike | None = None) -> Path:
    """``data`` as the file ``path``; ``root``: the folder the user gave, from which every folder
    down to ``path``'s is made or checked to be a real one (``own_folder``). A link or a hard link
    at ``path`` itself is replaced (a rename never follows one), its target left as it was."""
    path = Path(path)
    if root is None:
        path.parent.mkdir(parents=True, exist_ok=True)
    else:
        own_folder(root, path.parent)
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


def atomic_write_text(path: str | os.PathLike, text: str, *, root: str | os.PathLike | None = None) -> Path:
    return atomic_write_bytes(path, text.encode(), root=root)


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


def atomic_write_json(path: str | os.PathLike, obj: Any, *, indent: int | None = 2, exact: bool = False,
                      root: str | os.PathLike | None = None) -> Path:
    """JSON with numpy scalars unwrapped and non-finite floats made valid JSON (NaN -> null);
    ``exact``: ``obj`` as Python's json writes it (NaN / Infinity kept, to be read back exactly)."""
    return atomic_write_text(path, json.dumps(obj if exact else jsonable(obj), indent=indent) + "\n", root=root)


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


def atomic_save_figure(fig: Any, path: str | os.PathLike, *, root: str | os.PathLike | None = None,
                       **savefig_kwargs: Any) -> Path:
    """``fig.savefig`` written atomically, and the figure closed (pyplot keeps every open one in
    memory until the process ends); the format comes from ``path``'s suffix."""
    out = io.BytesIO()
    fig.savefig(out, format=Path(path).suffix.lstrip(".") or None, **savefig_kwargs)
    pyplot().close(fig)
    return atomic_write_bytes(path, out.getvalue(), root=root)


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
# Files inside a run, population, sweep or report directory. Such a directory is data from
# anywhere (a colleague's archive, a shared disk, a `cp -al` snapshot): a file or folder in it may
# be a symbolic link to something outside, a hard link to a file outside, a FIFO that blocks
# whoever opens it, a device or a huge file. Readers take only regular files of a bounded size.
# Writers go through one mechanism: the folders from the one the user gave down to the file are
# real folders (``own_folder``); whole files are replaced by a rename (``atomic_write_bytes``);
# a file written in place (a log appended to, a lock) is opened without following a link
# (``open_regular``) and, when it has another name (a hard link), first replaced by a copy of its
# own, so the other name never changes.

JSON_LIMIT = 16 << 20  # config.json, summary.json, population.json, a checkpoint's state.json, ...
SWEEP_JSON_LIMIT = 64 << 20  # sweep.json: a grid of thousands of trials, each with its log tail
CSV_LIMIT = 64 << 20
UNSHARE_LIMIT = 1 << 30  # the largest hard-linked file copied to be written in place (a run's log: LOG_LIMIT)


class UnsafeFileError(BotorlError):
    """A file botorl writes in a run directory is a symbolic link or not a regular file, or a
    folder on the way to it is a link."""


def _not_regular(path: Path, what: str) -> UnsafeFileError:
    return UnsafeFileError(
        f"{path} is {what}, not a regular file. botorl writes only regular files inside a run, population or "
        f"sweep directory (a link there could make it write anywhere); remove it and run the command again."
    )


def own_folder(root: str | os.PathLike, folder: str | os.PathLike, *, make: bool = True) -> Path:
    """``folder`` (``root`` or a folder under it), made if missing (``make``), with every folder
    from ``root`` down to it checked to be a real folder, not a symbolic link: ``root`` is the
    folder the user gave (taken as given: a link there is the user's own choice), and what botorl
    writes under it stays under it, whatever the directory holds. UnsafeFileError (exit 2) otherwise."""
    root, folder = Path(root), Path(folder)
    try:
        parts = folder.relative_to(root).parts
    except ValueError:
        parts = ("..",)
    if ".." in parts:
        raise UnsafeFileError(f"{folder} is not inside {root}; botorl writes only inside the folder it was given.")
    if make:
        root.mkdir(parents=True, exist_ok=True)
    here = root
    for part in parts:
        here = here / part
        if make:
            with contextlib.suppress(FileExistsError):
                os.mkdir(here)
        try:
            mode = os.lstat(here).st_mode
        except FileNotFoundError:
            if make:
                raise
            break  # nothing below it yet: nothing to check
        if not stat.S_ISDIR(mode):
            what = "a symbolic link" if stat.S_ISLNK(mode) else "not a folder"
            raise UnsafeFileError(
                f"{here} is {what}; botorl writes only into real folders inside {root} (a link there could make it "
                f"write anywhere). Remove it (or give another folder) and run the command again.")
    return folder


def unshare(path: str | os.PathLike, fd: int, prepare: Callable[[int], None] | None = None) -> int:
    """Replace ``path``, a hard link open as ``fd`` (perhaps for writing only), by a copy of its
    own (atomically, in its folder), so that writing to it leaves its other names as they were;
    returns the copy's fd (read-write, at its end) and closes ``fd`` (on an error ``fd`` stays
    open, the caller's). ``prepare(new_fd)`` runs before the rename (a lock takes its flock there)."""
    path = Path(path)
    size = os.fstat(fd).st_size
    if size > UNSHARE_LIMIT:
        raise UnsafeFileError(
            f"{path} is a hard link ({size:,} bytes, shared with a file outside this folder or a copy made with "
            f"`cp -al`); botorl writes only files of its own. Make a real copy of the directory (`cp -a`) and run the "
            f"command on that.")
    src = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    new, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        if os.fstat(src).st_ino != os.fstat(fd).st_ino:
            raise UnsafeFileError(f"{path} changed while botorl opened it; run the command again.")
        os.fchmod(new, 0o666 & ~_UMASK)
        while chunk := os.read(src, 1 << 20):
            os.write(new, chunk)
        os.fsync(new)
        if prepare is not None:
            prepare(new)
        os.replace(tmp, path)
    except BaseException:
        os.close(new)
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    finally:
        os.close(src)
    os.close(fd)
    return new


def open_regular(path: str | os.PathLike, flags: int, mode: int = 0o644, *, root: str | os.PathLike | None = None,
                 shared: bool = False) -> int:
    """``os.open`` of a regular file that follows no symbolic link and never blocks on a FIFO
    (``O_NONBLOCK``: a FIFO or device is opened, seen and closed); ``UnsafeFileError`` (exit 2)
    otherwise. ``root``: the folder the user gave (``own_folder`` checks the way down). Opened for
    writing, a hard link is first replaced by a copy of its own (``unshare``) unless ``shared``
    (the caller does it: ``RunLock``, under its flock)."""
    path = Path(path)
    if root is not None:
        own_folder(root, path.parent)
    try:  # O_TRUNC after the checks below: truncating a hard link empties its other names too
        fd = os.open(path, flags & ~os.O_TRUNC | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, mode)
    except OSError as err:
        # ENXIO: a FIFO without a reader, opened for writing
        what = {errno.ELOOP: "a symbolic link", errno.ENXIO: "a FIFO", errno.EISDIR: "a directory"}.get(err.errno)
        if what is None:
            raise
        raise _not_regular(path, what) from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise _not_regular(path, "a directory" if stat.S_ISDIR(st.st_mode) else "a special file")
        if st.st_nlink > 1 and flags & (os.O_WRONLY | os.O_RDWR) and not shared:
            fd, copy = -1, unshare(path, fd)  # unshare closed the link's fd
            os.close(copy)
            return open_regular(path, flags, mode, shared=True)  # the copy, now the only name of its file
        if flags & os.O_TRUNC:
            os.ftruncate(fd, 0)
    except BaseException:
        if fd >= 0:
            os.close(fd)
        raise
    return fd


def append_text(path: str | os.PathLike, text: str, *, root: str | os.PathLike | None = None) -> None:
    """Append ``text`` to the regular file ``path`` (created if missing), following no link and
    writing no other name of it (``open_regular``)."""
    fd = open_regular(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666 & ~_UMASK, root=root)
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
        while left > 0 and (b := os.read(fd, min(left, 1 << 20))):  # to the end, at most limit bytes
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


def csv_text(header: Sequence[str] | None, rows: Iterable[Sequence[Any]]) -> str:
    """CSV text of ``rows`` under ``header`` (None: no header row, for rows appended to a log)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    if header is not None:
        w.writerow(header)
    w.writerows(rows)
    return buf.getvalue()


def read_json_object(path: str | os.PathLike, limit: int = JSON_LIMIT) -> dict[str, Any] | None:
    """The JSON object in ``path`` (a regular file of at most ``limit`` bytes), else None: for
    files botorl may find missing, cut short or not its own (a sweep's, a run's being written).
    Never for a record that nothing else holds, which must not be taken for none and replaced
    (sweep.json: ``Sweep.earlier_manifest``, exit 2)."""
    try:
        data = read_json_bounded(path, limit)
        return data if isinstance(data, dict) else None
    except (OSError, ValueError):
        return None

"""Checks a data file passes before botorl reads it: a data path can come from a run
directory's config.json, which is data, never orders. Only a regular file is opened (a FIFO would
hang the reader, a device would be read without end), and it is sized before it is hashed or
read; a ``.npz`` is sized from its headers before any array is inflated, every member whatever its
name; an HDF5 file that stores data outside itself (external storage, external links, virtual
datasets) or holds a soft link that leads nowhere is refused, since it could make botorl read any
file or a FIFO. A file whose arrays inflate far beyond its bytes on disk (a few MB of deflate that
declare gigabytes) is refused whatever the machine's memory: no offline RL dataset compresses so.
A pickle (Cal-QL's ``.npy`` object arrays, DAPG's demos) is read by ``read_plain_pickle`` alone, which
builds nothing but plain data: a pickle that names any other callable is refused before it is called.
"""

from __future__ import annotations

import codecs
import collections
import hashlib
import os
import pickle
import resource
import stat
import zipfile
from pathlib import Path

import h5py
import numpy as np

from botorl.errors import DataFormatError

MAX_DATA_BYTES = 64 << 30  # one dataset's arrays: far above any offline RL dataset botorl reads
# Inflation: a file may declare up to INFLATE_FREE bytes of arrays whatever it holds on disk, more
# only at most MAX_INFLATION times its size (float data deflate about 1.1-3x; a deflated run of
# zeros 1000x, which is how a few MB declare gigabytes).
INFLATE_FREE = 256 << 20
MAX_INFLATION = 100


def machine_memory() -> int:
    """Bytes of physical memory (0 when the system does not say)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 0


def data_cap() -> int:
    """Bytes a dataset may declare: ``MAX_DATA_BYTES``, at most half this machine's memory (and of
    the process's address-space limit)."""
    have = machine_memory()
    cap = min(MAX_DATA_BYTES, have // 2) if have else MAX_DATA_BYTES
    try:  # a process under `ulimit -v` has less than the machine
        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
        if soft != resource.RLIM_INFINITY:
            cap = min(cap, soft // 2)
    except (ValueError, OSError):
        pass
    return cap


def regular_file(path: str | os.PathLike, what: str = "data file") -> Path:
    """``path`` if it is a regular file (a link to one is fine) of at most ``data_cap()`` bytes,
    else DataFormatError naming it (and its size and the cap)."""
    p = Path(path)
    try:
        st = os.stat(p)
    except OSError as err:
        raise DataFormatError(f"{p}: the {what} cannot be opened ({err.strerror}).") from None
    if not stat.S_ISREG(st.st_mode):
        kind = "a folder" if stat.S_ISDIR(st.st_mode) else "not a regular file (a FIFO, device or socket)"
        raise DataFormatError(f"{p}: the {what} is {kind}; botorl reads data only from regular files.")
    cap = data_cap()
    if st.st_size > cap:
        raise DataFormatError(f"{p}: the {what} is {st.st_size:,} bytes, more than botorl reads ({cap:,} bytes, "
                              f"{cap / 2**30:.1f} GiB); give a smaller file.")
    return p


def check_inflation(path: Path, declared: int, what: str = "arrays") -> None:
    """DataFormatError when ``declared`` bytes of arrays are more than ``INFLATE_FREE`` and more
    than ``MAX_INFLATION`` times ``path``'s size on disk (a compression bomb)."""
    on_disk = os.stat(path).st_size
    if declared > max(INFLATE_FREE, MAX_INFLATION * on_disk):
        raise DataFormatError(f"{path}: its {what} declare {declared:,} bytes from {on_disk:,} on disk, more than "
                              f"{MAX_INFLATION}x; no dataset compresses so (a compression bomb?). Save the data "
                              f"uncompressed (np.savez, an HDF5 file without gzip).")


def check_npz(path: str | os.PathLike) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """The arrays of a ``.npz`` (name -> (shape, dtype)) from their headers, without inflating
    them; DataFormatError for a file that is no plain zip of ``.npy`` arrays (a member of any
    other name: np.load would inflate it unchecked), holds object arrays (a pickle), declares more
    bytes than ``data_cap()``, more than it holds or far more than its size (``check_inflation``),
    or names an array both as a leaf and as a group (``observations`` and ``observations/goal``)."""
    p = regular_file(path, ".npz file")
    cap = data_cap()
    out: dict[str, tuple[tuple[int, ...], np.dtype]] = {}
    total = 0
    try:
        with zipfile.ZipFile(p) as z:
            infos = z.infolist()
            other = next((i.filename for i in infos if not i.filename.endswith(".npy")), None)
            if other is not None:
                raise DataFormatError(f"{p}: member {other[:200]!r} is not a .npy array; a .npz botorl reads holds "
                                      f"only arrays (np.savez writes them).")
            check_inflation(p, sum(i.file_size for i in infos), "members")  # what the zip says they inflate to
            for info in infos:
                with z.open(info) as f:
                    fmt = np.lib.format
                    v1 = fmt.read_magic(f) == (1, 0)
                    shape, _, dtype = (fmt.read_array_header_1_0 if v1 else fmt.read_array_header_2_0)(f)
                    header = f.tell() if f.seekable() else None
                if dtype.hasobject:
                    raise DataFormatError(f"{p}: array {info.filename[:-4]!r} holds Python objects (a pickle); save "
                                          f"plain numeric arrays with np.savez.")
                size = int(np.prod(shape, dtype=object)) * dtype.itemsize
                total += size
                if total > cap:
                    raise DataFormatError(f"{p}: its arrays declare {total / 2**30:.1f} GiB, more than botorl reads "
                                          f"({cap / 2**30:.1f} GiB); give a smaller dataset.")
                if header is not None and size > info.file_size - header:
                    raise DataFormatError(f"{p}: array {info.filename[:-4]!r} declares {size:,} bytes and holds "
                                          f"{info.file_size - header:,}; the file is truncated or damaged.")
                out[info.filename[:-4]] = (tuple(shape), dtype)
    except DataFormatError:
        raise
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, NotImplementedError, KeyError) as err:
        raise DataFormatError(f"{p}: not a readable .npz file ({type(err).__name__}: {err}).") from None
    for name in out:
        if any(other.startswith(name + "/") for other in out):
            raise DataFormatError(f"{p}: {name!r} is both an array and a group of arrays ({name}/...); keep one.")
    return out


def check_hdf5(f, path) -> None:
    """DataFormatError when the open h5py file ``f`` stores data outside itself (external links,
    external storage, virtual datasets), holds a link that leads nowhere (to itself, to nothing) or
    declares more than ``data_cap()`` bytes, or far more than its size (``check_inflation``)."""
    cap = data_cap()
    total = 0
    todo = [f]
    while todo:
        group = todo.pop()
        for name in group:
            link = group.get(name, getlink=True)
            if isinstance(link, h5py.ExternalLink):
                raise DataFormatError(f"{path}: {group.name.rstrip('/')}/{name} links to another file "
                                      f"({link.filename}); botorl reads only data stored in the file itself.")
            try:
                node = group[name]
            except (KeyError, RuntimeError, OSError, ValueError) as err:  # a soft link to itself or to nothing
                raise DataFormatError(f"{path}: {group.name.rstrip('/')}/{name} cannot be opened ({err}): a link "
                                      f"that leads nowhere; remove it from the file.") from None
            if isinstance(link, h5py.SoftLink):
                continue  # a name for something in this file, visited where it lives
            if isinstance(node, h5py.Group):
                todo.append(node)
                continue
            if not isinstance(node, h5py.Dataset):
                continue
            if node.external or node.is_virtual:
                raise DataFormatError(f"{path}: dataset {node.name} is stored outside the file (external storage or "
                                      f"a virtual dataset); botorl reads only data stored in the file itself.")
            total += int(np.prod(node.shape or (1,), dtype=object)) * node.dtype.itemsize
            if total > cap:
                raise DataFormatError(f"{path}: its datasets declare {total / 2**30:.1f} GiB, more than botorl reads "
                                      f"({cap / 2**30:.1f} GiB).")
    check_inflation(Path(path), total, "datasets")


def data_files(path: str | os.PathLike, minari_root: Path | None = None) -> list[Path]:
    """The files a run reads for its ``data.path``: the file itself; a Minari dataset's
    ``main_data.hdf5`` (a folder, its ``data`` folder or an id under ``minari_root``); the regular
    files directly inside any other folder (the Cal-QL folder); each of ``a,b``. Nothing for a
    path that does not exist (the loader names it)."""
    p = Path(path).expanduser()
    if not p.exists() and "," in str(path):
        return [f for part in str(path).split(",") if part for f in data_files(part, minari_root)]
    if p.is_file() or (p.exists() and not p.is_dir()):
        return [p]
    if not p.exists():
        if minari_root is None:
            return []
        p = Path(minari_root) / str(path)
        if not p.is_dir():
            return []
    for main in (p / "data" / "main_data.hdf5", p / "main_data.hdf5"):
        if os.path.lexists(main):
            return [main]
    return [e for e in sorted(p.iterdir())[:10_000] if e.is_file() and stat.S_ISREG(e.stat().st_mode)]


def fingerprint(path: str | os.PathLike | None, minari_root: Path | None = None) -> dict:
    """``{"path", "size", "sha256"}`` of what a run reads for ``data.path`` (``data_files``; None:
    the task's own data, made or named by botorl, which the config's digest covers). An integrity
    check: it says the data did not change, not who made them. Every file is sized before any is
    hashed (a 1 TB sparse file is refused at once, not read for minutes)."""
    if path is None:
        return {"path": None}
    h = hashlib.sha256()
    size = 0
    try:
        files = data_files(path, minari_root)
        if sum(regular_file(f).stat().st_size for f in files) > data_cap():
            raise DataFormatError(f"data.path {path}: its files hold more than botorl reads ({data_cap() / 2**30:.1f} "
                                  f"GiB, half this machine's memory at most); give a smaller dataset.")
        for f in files:
            with open(f, "rb") as fh:
                size += os.fstat(fh.fileno()).st_size
                h.update(f.name.encode() + b"\0")
                h.update(hashlib.file_digest(fh, "sha256").digest())
    except OSError as err:
        raise DataFormatError(f"data.path {path}: cannot be read to check it ({err}).") from None
    return {"path": str(path), "size": size, "sha256": h.hexdigest()}


# ----------------------------------------------------------------------------- pickles
# What a pickle may build here: dicts, lists, tuples, numbers, strings, bytes, bools and None (pickle's
# own opcodes, which name no callable) and NumPy arrays, scalars and dtypes. These are the globals their
# pickles name, as NumPy 1 (numpy.core) and 2 (numpy._core) spell them, each mapped to the very object
# (taken from NumPy's own pickles, so no module a file names is imported); ``_codecs.encode`` and
# ``bytes()`` are how a protocol-2 pickle spells bytes and empty bytes, and OrderedDict is a plain dict.


def _latin1(text, encoding="latin1"):
    if encoding not in ("latin1", "latin-1") or not isinstance(text, str):
        raise pickle.UnpicklingError(f"_codecs.encode with encoding {encoding!r}")
    return codecs.encode(text, "latin1")


def _empty_bytes() -> bytes:
    return b""


def _plain_globals() -> dict[tuple[str, str], object]:
    table = {("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype, ("_codecs", "encode"): _latin1,
             ("collections", "OrderedDict"): collections.OrderedDict, ("builtins", "bytes"): _empty_bytes,
             ("__builtin__", "bytes"): _empty_bytes}
    for core in ("numpy.core", "numpy._core"):
        table[(f"{core}.multiarray", "_reconstruct")] = np.ndarray((0,)).__reduce__()[0]
        table[(f"{core}.multiarray", "scalar")] = np.float64(0).__reduce__()[0]
        table[(f"{core}.numeric", "_frombuffer")] = np.zeros(1).__reduce_ex__(5)[0]
    return table


_PLAIN_GLOBALS = _plain_globals()


class _PlainUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        try:
            return _PLAIN_GLOBALS[(module, name)]
        except (KeyError, TypeError):
            raise DataFormatError(f"names {module}.{name}") from None


def read_plain_pickle(path: Path, what: str):
    """The data a pickle file holds (``.npy``: an object array's), built only from plain containers,
    numbers, strings and NumPy arrays; DataFormatError when it names anything else, which is never
    called (a pickle's callables can run any code)."""
    with open(path, "rb") as fh:
        try:
            if path.suffix == ".npy":
                version = np.lib.format.read_magic(fh)
                read_header = {(1, 0): np.lib.format.read_array_header_1_0,
                               (2, 0): np.lib.format.read_array_header_2_0}.get(version)
                if read_header is None:
                    raise ValueError(f".npy format version {version}, which botorl does not read")
                read_header(fh)
            # latin1: the bytes of arrays a Python 2 pickle stored as str (NumPy's advice for np.load)
            return _PlainUnpickler(fh, encoding="latin1").load()
        except DataFormatError as err:
            raise DataFormatError(f"{path}: this {what} {err}, which botorl does not load: botorl unpickles only "
                                  "dicts, lists, tuples, numbers, strings and NumPy arrays, as anything else a pickle "
                                  "names could run code. Convert the file to a .npz of plain arrays.") from None

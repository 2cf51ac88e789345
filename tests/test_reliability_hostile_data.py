"""Data files a run directory can name are data too (issue 39): only regular files are opened
(a FIFO would hang the reader), HDF5 files that store data outside themselves are refused, a
``.npz`` is sized from its headers before any array is inflated, and a malformed file is exit 2
with a message, never a traceback. Each case here hung, read another file or raised a traceback
before issue 39."""

from __future__ import annotations

import io
import os
import zipfile
from pathlib import Path

import numpy as np
import pytest

from botorl.cli import main as botorl_main
from botorl.errors import DataFormatError


def _info(capsys, path) -> str:
    code = botorl_main(["data", "info", str(path)])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err, err
    return err


def _d4rl(path: Path, **override) -> Path:
    import h5py

    n = 20
    with h5py.File(path, "w") as f:
        fields = {"observations": np.zeros((n, 3), np.float32), "actions": np.zeros((n, 2), np.float32),
                  "rewards": np.zeros(n, np.float32), "terminals": np.zeros(n, bool)}
        fields.update(override)
        for k, v in fields.items():
            if v is not None:
                f.create_dataset(k, data=v)
    return path


@pytest.mark.timeout(60)
def test_fifos_are_never_opened(tmp_path, capsys):
    fifo = tmp_path / "data.hdf5"
    os.mkfifo(fifo)
    assert "not a regular file" in _info(capsys, fifo)
    # a Minari folder whose main_data.hdf5 is a FIFO (hung --data.path)
    ds = tmp_path / "minari" / "data"
    ds.mkdir(parents=True)
    os.mkfifo(ds / "main_data.hdf5")
    (ds / "metadata.json").write_text("{}")
    assert "not a regular file" in _info(capsys, tmp_path / "minari")
    for name in ("x.npy", "x.npz"):
        os.mkfifo(tmp_path / name)
        assert "not a regular file" in _info(capsys, tmp_path / name)


@pytest.mark.timeout(60)
def test_hdf5_external_storage_and_links_are_refused(tmp_path, capsys):
    import h5py

    secret = tmp_path / "secret.bin"
    secret.write_bytes(np.arange(20, dtype=np.float32).tobytes())
    ext = _d4rl(tmp_path / "ext.hdf5", rewards=None)
    with h5py.File(ext, "a") as f:  # rewards read from another file (it could be /etc/passwd, or a FIFO)
        f.create_dataset("rewards", shape=(20,), dtype=np.float32, external=[(str(secret), 0, 80)])
    assert "stored outside the file" in _info(capsys, ext)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    hang = _d4rl(tmp_path / "hang.hdf5", rewards=None)
    with h5py.File(hang, "a") as f:
        f.create_dataset("rewards", shape=(20,), dtype=np.float32, external=[(str(fifo), 0, 80)])
    assert "stored outside the file" in _info(capsys, hang)
    link = _d4rl(tmp_path / "link.hdf5", rewards=None)
    other = _d4rl(tmp_path / "other.hdf5")
    with h5py.File(link, "a") as f:
        f["rewards"] = h5py.ExternalLink(str(other), "/rewards")
    assert "links to another file" in _info(capsys, link)
    # control: the plain file reads
    assert botorl_main(["data", "info", str(_d4rl(tmp_path / "plain.hdf5"))]) == 0


def test_bytes_where_numbers_belong_is_exit_2(tmp_path, capsys):
    bad = _d4rl(tmp_path / "bytes.hdf5", rewards=np.array([b"abc"] * 20))
    assert "cannot be read as numbers" in _info(capsys, bad)


# ----------------------------------------------------------------------------- .npz
def _task():
    from botorl.envs.user import UserTask

    return UserTask(obs_keys=None, obs_dim=3, action_dim=2, action_low=(-1.0, -1.0), action_high=(1.0, 1.0),
                    success_key=None)


def _arrays(n=10):
    return {"observations": np.zeros((n, 3), np.float32), "actions": np.zeros((n, 2), np.float32),
            "rewards": np.zeros(n, np.float32), "next_observations": np.zeros((n, 3), np.float32),
            "terminals": np.zeros(n, np.float32)}


def _npy_bytes(shape, dtype="<f4", body=b"") -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": dtype, "fortran_order": False, "shape": shape})
    return buf.getvalue() + body


def _load(path):
    from botorl.data.user import load_file

    return load_file(path, _task())


def test_npz_headers_are_checked_before_reading(tmp_path):
    good = tmp_path / "good.npz"
    np.savez(good, **_arrays())
    assert len(_load(good).rewards) == 10  # control

    # a header declaring 2^40 rows over a few bytes: refused from the header, nothing inflated
    huge = tmp_path / "huge.npz"
    with zipfile.ZipFile(huge, "w") as z:
        for k, v in _arrays().items():
            z.writestr(f"{k}.npy", _npy_bytes((2**40, 3)) if k == "observations" else _npy_bytes(v.shape, body=v.tobytes()))
    with pytest.raises(DataFormatError, match="GiB, more than botorl reads"):
        _load(huge)

    # a zip bomb: 100 MB of zeros in a small file, refused under a 64 MiB cap before it is inflated
    import botorl.data.safe as safe

    bomb = tmp_path / "bomb.npz"
    with zipfile.ZipFile(bomb, "w", compression=zipfile.ZIP_DEFLATED) as z:
        for k, v in _arrays().items():
            z.writestr(f"{k}.npy", _npy_bytes((25_000_000, 1)) + b"\0" * 100_000_000 if k == "rewards"
                       else _npy_bytes(v.shape, body=v.tobytes()))
    assert bomb.stat().st_size < 1_000_000
    old = safe.MAX_DATA_BYTES
    safe.MAX_DATA_BYTES = 64 << 20
    try:
        with pytest.raises(DataFormatError, match="more than botorl reads"):
            _load(bomb)
    finally:
        safe.MAX_DATA_BYTES = old

    both = tmp_path / "both.npz"
    np.savez(both, **_arrays(), **{"observations/goal": np.zeros((10, 1), np.float32)})
    with pytest.raises(DataFormatError, match="both an array and a group"):
        _load(both)

    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(DataFormatError, match="not a readable .npz"):
        _load(truncated)

    text = tmp_path / "text.npz"
    np.savez(text, **{**_arrays(), "rewards": np.array(["a"] * 10)})
    with pytest.raises(DataFormatError):
        _load(text)

    objects = tmp_path / "objects.npz"
    with zipfile.ZipFile(objects, "w") as z:
        z.writestr("observations.npy", _npy_bytes((10, 3), dtype="|O"))
    with pytest.raises(DataFormatError, match="Python objects"):
        _load(objects)


def test_minari_bytes_actions_are_exit_2_not_a_traceback(tmp_path, capsys):
    """A Minari dataset (botorl's writer) whose first episode's actions were replaced by bytes."""
    import h5py

    from botorl.data.dataset import Dataset
    from botorl.data.minari_io import write_minari

    n = 6
    ds = Dataset(np.zeros((n, 3), np.float32), np.zeros((n, 2), np.float32), np.zeros(n, np.float32),
                 np.zeros((n, 3), np.float32), np.zeros(n, bool), np.arange(n) == n - 1, metadata={"source": "mem"})
    folder = write_minari(ds, path=tmp_path / "mine-v0")
    for f in folder.glob("botorl_flat*"):
        f.unlink()  # read the episodes themselves
    with h5py.File(folder / "data" / "main_data.hdf5", "a") as f:
        g = f["episode_0"]
        del g["actions"]
        g.create_dataset("actions", data=np.array([b"ab"] * n))
    assert "cannot be read as numbers" in _info(capsys, folder)

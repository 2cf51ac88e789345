"""Caches are checked against their source before they are trusted; damaged datasets exit 2.

- botorl_flat.npz records the size and sha256 of main_data.hdf5 and a checksum of its rows;
  a tampered copy (actions x50, a forged action range, an older unchecked copy) is rebuilt
  from the Minari data with a warning.
- a `data generate` killed with -9 leaves a temporary root that the next write removes.
- a truncated or empty main_data.hdf5 is a DataFormatError (exit 2), not an h5py traceback;
  `run --data.path FILE` says what is wrong with the file instead of "not found".
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from botorl.cli import main as botorl_main
from botorl.data.dataset import Dataset
from botorl.data.loaders import load_minari
from botorl.data.minari_io import FLAT_FILE, FlatCacheInvalid, _content_sha256, read_flat, write_minari
from botorl.errors import DataFormatError

REPO = Path(__file__).resolve().parents[1]
FIELDS = ("observations", "actions", "rewards", "next_observations", "terminals", "episode_ends")


def _ds(n=12):
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(n + 1, 3)).astype(np.float32)
    ends = np.zeros(n, bool)
    ends[[5, n - 1]] = True
    nobs = obs[1:].copy()
    return Dataset(obs[:-1], rng.uniform(-0.5, 0.5, size=(n, 2)), rng.normal(size=n), nobs, np.zeros(n, bool), ends,
                   infos={"success": np.zeros(n, np.float32)}, metadata={"source": "mem"})


@pytest.fixture()
def written(tmp_path):
    ds = _ds()
    path = write_minari(ds, path=tmp_path / "unit" / "steps12-seed0-v0", metadata={"generator": "unit"})
    return ds, path


def _rewrite_flat(path: Path, change, *, fix_checksum: bool) -> None:
    with np.load(path / FLAT_FILE, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    change(arrays)
    if fix_checksum:  # a careful forger recomputes the rows' checksum
        body = {k: v for k, v in arrays.items() if k not in ("content_sha256", "source_size", "source_sha256")}
        arrays["content_sha256"] = np.asarray(_content_sha256(body))
    np.savez(path / FLAT_FILE, **arrays)


def _same(a: Dataset, b: Dataset) -> None:
    for k in FIELDS:
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)


def test_flat_cache_verified(written):
    ds, path = written
    assert read_flat(path) is not None
    _same(load_minari(path), ds)


@pytest.mark.parametrize("fix_checksum", [False, True])
def test_tampered_flat_actions_are_rebuilt(written, capsys, fix_checksum):
    ds, path = written

    def times_50(a):
        a["actions"] = a["actions"] * 50

    _rewrite_flat(path, times_50, fix_checksum=fix_checksum)
    with pytest.raises(FlatCacheInvalid):
        read_flat(path)
    back = load_minari(path)
    assert "not using the flat cache" in capsys.readouterr().err
    _same(back, ds)  # the Minari rows, not the x50 ones
    assert read_flat(path) is not None  # rebuilt


def test_forged_action_range_is_caught(written):
    _, path = written

    def forge(a):  # actions x50 clipped and a matching "raw" range claimed... but not matching the data
        a["actions"] = np.clip(a["actions"] * 50, -1 + 1e-5, 1 - 1e-5).astype(a["actions"].dtype)
        a["raw_action_max"] = np.asarray(0.5)

    _rewrite_flat(path, forge, fix_checksum=True)
    with pytest.raises(FlatCacheInvalid, match="action range"):
        read_flat(path)


def test_flat_made_from_another_source_or_unchecked(written, capsys):
    ds, path = written

    def legacy(a):
        for k in ("content_sha256", "source_size", "source_sha256"):
            a.pop(k)

    _rewrite_flat(path, legacy, fix_checksum=False)
    with pytest.raises(FlatCacheInvalid, match="without checksums"):
        read_flat(path)
    _same(load_minari(path), ds)
    read_flat(path)

    def other(a):
        a["source_size"] = np.asarray(int(a["source_size"]) + 1, np.int64)

    _rewrite_flat(path, other, fix_checksum=False)
    with pytest.raises(FlatCacheInvalid, match="different"):
        read_flat(path)


def test_truncated_and_empty_minari_file_exit_2(written, capsys):
    _, path = written
    main = path / "data" / "main_data.hdf5"
    main.write_bytes(main.read_bytes()[: main.stat().st_size // 2])
    with pytest.raises(DataFormatError, match="truncated or damaged|not a readable Minari"):
        load_minari(path)
    assert botorl_main(["data", "info", str(path)]) == 2
    assert botorl_main(["run", "--task", "pointmaze-umaze", "--profile", "smoke", "--data.path", str(path)]) == 2
    main.write_bytes(b"")
    assert botorl_main(["data", "info", str(path)]) == 2
    assert botorl_main(["data", "info", str(main)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and str(main) in err


def test_run_data_path_existing_file_is_not_not_found(tmp_path, capsys):
    f = tmp_path / "existing.hdf5"
    f.write_bytes(b"\x89HDF\r\n")
    assert botorl_main(["run", "--task", "pointmaze-umaze", "--profile", "smoke", "--data.path", str(f)]) == 2
    err = capsys.readouterr().err
    assert "not found" not in err and "exists" in err and str(f) in err
    d = tmp_path / "folder"
    d.mkdir()
    assert botorl_main(["run", "--task", "pointmaze-umaze", "--profile", "smoke", "--data.path", str(d)]) == 2
    err = capsys.readouterr().err
    assert "not found" not in err and "not a Minari dataset folder" in err


_KILLED_WRITER = """
import sys, time
import numpy as np
from botorl.data import minari_io
from botorl.data.dataset import Dataset
def hang(*a, **k):
    print("writing", flush=True)
    time.sleep(300)
minari_io._write_flat = hang
n = 4
ds = Dataset(np.zeros((n, 2)), np.zeros((n, 1)), np.zeros(n), np.zeros((n, 2)), np.zeros(n, bool), np.ones(n, bool))
minari_io.write_minari(ds, "botorl/unit/steps4-seed0-v0", root=sys.argv[1])
"""


def test_killed_writer_leaves_no_temp_dir_for_long(tmp_path):
    root = tmp_path / "root"
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, "-c", _KILLED_WRITER, str(root)], env=env, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "writing"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    left = [p for p in root.iterdir() if p.name.startswith(".botorl-tmp-")]
    assert len(left) == 1  # kill -9: no finally ran
    live = root / f".botorl-tmp-{left[0].name.split('-')[2]}-{os.getpid()}-alive"
    live.mkdir()  # a writer that is still running (this process) is left alone
    write_minari(_ds(), "botorl/unit/steps12-seed1-v0", root=root)
    names = {p.name for p in root.iterdir() if p.name.startswith(".botorl-tmp-")}
    assert names == {live.name}



def test_door_demos_ship_with_the_package(monkeypatch):
    """door-binary-local finds its demos inside the package, with $BOTORL_DOOR_DEMOS unset."""
    import hashlib

    from botorl.data.generators import door

    monkeypatch.delenv(door.ENV_VAR, raising=False)
    path = door.find_demos()
    assert path == door.SHIPPED_DEMOS and REPO / "botorl" in path.parents
    assert hashlib.sha256(path.read_bytes()).hexdigest() == (
        "028df28fe11c084228f0a31cee1a9792c371c3c98cce3061c8ebb79af3460cdd")  # /work/shared/data/README.md
    demos = door.load_demos(path)  # plain .npz, no pickle
    assert len(demos) == 25
    assert (path.parent / "NOTICE").is_file() and "Apache" in (path.parent / "README.md").read_text()
    pyproject = (REPO / "pyproject.toml").read_text()
    assert '"assets/door_human_demos.npz"' in pyproject  # installed as package data
    # an explicit path still wins
    monkeypatch.setenv(door.ENV_VAR, str(path))
    assert door.find_demos() == path

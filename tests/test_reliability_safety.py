"""A run directory is data, never code; it has one owner; user errors and I/O faults exit 2.

Each test fails on the code before issue 15: the crafted config.json ran its pickle, two
processes shared one --out, and --seed -1, a closed stdout and a read-only --out ended in
tracebacks.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from botorl.cli import main as botorl_main
from botorl.errors import DataFormatError
from helpers import Payload

REPO = Path(__file__).resolve().parents[1]


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _evil_npy(path: Path, marker: Path) -> Path:
    arr = np.empty(1, dtype=object)
    arr[0] = Payload(marker)
    np.save(path, arr, allow_pickle=True)
    return path


def _crafted_run_dir(tmp_path: Path, data_path: Path) -> Path:
    from botorl.configs.schema import to_dict
    from botorl.pipeline.cli import build_config

    cfg = build_config(["--task", "door-binary-v0", "--profile", "smoke", "--data.path", str(data_path)])
    d = tmp_path / "crafted"
    d.mkdir()
    (d / "config.json").write_text(json.dumps(to_dict(cfg)))
    from botorl.pipeline.checkpoint import CheckpointManager

    # a (data-less) checkpoint, so that `eval` gets as far as loading the data
    CheckpointManager(d / "checkpoints").save("pretrain-final", state={"stage": "pretrain", "step": None,
                                                                       "stage_done": True, "done_stages": ["pretrain"]})
    return d


def test_crafted_config_does_not_unpickle(tmp_path, capsys):
    marker = tmp_path / "pwned"
    evil = _evil_npy(tmp_path / "door2_sparse.npy", marker)
    d = _crafted_run_dir(tmp_path, evil)
    for cmd in (["resume", str(d)], ["eval", str(d)]):
        assert botorl_main(cmd) == 2
        err = capsys.readouterr().err
        assert "pickle" in err and "--allow-pickle" in err and str(evil) in err
        assert not marker.exists()
    # opted in, the file is read, but by the restricted unpickler (issue 51): refused, nothing runs
    assert botorl_main(["resume", str(d), "--allow-pickle"]) == 2
    assert "names io.open" in capsys.readouterr().err and not marker.exists()
    # control: NumPy's own loader does run the payload, so the checks above can fail
    np.load(evil, allow_pickle=True)
    assert marker.exists()


def test_npy_without_pickle_is_read_without_pickle(tmp_path):
    """A plain (non-object) .npy is read with allow_pickle=False even where pickle is refused."""
    from botorl.data.loaders import _load_pickle_array, refuse_pickle

    p = tmp_path / "plain.npy"
    np.save(p, np.arange(6, dtype=np.float32))
    with refuse_pickle("a test"):
        assert _load_pickle_array(p, "array").tolist() == list(range(6))
        evil = _evil_npy(tmp_path / "evil.npy", tmp_path / "m")
        with pytest.raises(DataFormatError, match="a test"):
            _load_pickle_array(evil, "array")
    assert not (tmp_path / "m").exists()


def test_adroit_hint_names_the_real_flag():
    from botorl.data.loaders import download_hint
    from botorl.data.tasks import data_status
    from botorl.envs.registry import get_task

    assert "--data.path" in download_hint("door-binary-v0") and "--data-path" not in download_hint("door-binary-v0")
    assert "--data.path" in data_status(get_task("door-binary-v0"))[1]


# ----------------------------------------------------------------------------- lock
_HOLD = ("import sys, time; from botorl.pipeline.rundir import RunLock; RunLock(sys.argv[1]).acquire(); "
         "print('held', flush=True); time.sleep(120)")


def test_run_dir_has_one_owner(tmp_path):
    from botorl.pipeline.rundir import LOCK_FILE, RunLock, RunLockedError

    d = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, str(d)], env=_env(), stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(RunLockedError, match=f"PID {holder.pid}"):
            RunLock(d).acquire()
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=30)
    # the kernel dropped the dead holder's flock: the stale lock is taken over
    with RunLock(d) as lock:
        assert (d / LOCK_FILE).read_text().strip() == str(os.getpid())
        with pytest.raises(RunLockedError):
            RunLock(d).acquire()  # a second owner in the same process is refused too
    RunLock(d).acquire().release()


def test_second_run_on_same_out_exits_2(tmp_path, capsys):
    """Two `botorl run` with one --out: the second gets exit 2 naming the first's PID."""
    d = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, str(d)], env=_env(), stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        rc = botorl_main(["run", "--task", "pointmaze-umaze", "--profile", "smoke", "--no-progress",
                          "--no-tensorboard", "--out", str(d)])
        err = capsys.readouterr().err
        assert rc == 2
        assert f"PID {holder.pid}" in err and "in use" in err
        assert not (d / "config.json").exists()
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=30)


# ----------------------------------------------------------------------------- exit 2
def test_negative_seed_exits_2(capsys):
    assert botorl_main(["run", "--task", "pointmaze-umaze", "--profile", "smoke", "--seed", "-1"]) == 2
    assert "--seed = -1" in capsys.readouterr().err


def test_help_into_closed_pipe_has_no_traceback():
    r, w = os.pipe()
    os.close(r)  # the reader is gone before botorl writes a byte (like `| head` after its lines)
    proc = subprocess.run([sys.executable, "-m", "botorl.cli", "run", "--help"], stdout=w, stderr=subprocess.PIPE,
                          env=_env(), text=True, timeout=120)
    os.close(w)
    assert "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert proc.returncode == 2


def test_unwritable_out_at_start_exits_2(tmp_path, capsys):
    """An --out the process may not create (here under /sys: EPERM/EROFS even for root)."""
    if not Path("/sys").is_dir():
        pytest.skip("no /sys")
    out = Path("/sys/botorl-test-run")
    rc = botorl_main(["run", "--task", "pointmaze-umaze", "--profile", "smoke", "--no-progress",
                      "--no-tensorboard", "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert str(out) in err and "Traceback" not in err


@pytest.mark.parametrize("code, words", [(errno.ENOSPC, "disk is full"), (errno.EROFS, "read-only")])
def test_disk_full_mid_run_exits_2_and_marks_failed(tmp_path, capsys, monkeypatch, code, words):
    """ENOSPC / EROFS while a checkpoint is written: exit 2 naming the directory; summary.json says failed.
    (A real read-only remount under a running process is refused by the kernel while files are
    open for writing, so the fault is injected; test_reliability_diskfull fills a real disk.)"""
    from botorl.pipeline import checkpoint as ck

    real_save = ck.CheckpointManager.save
    calls = {"n": 0}

    def full_disk(self, name, **kw):
        calls["n"] += 1
        if calls["n"] >= 2:  # the first checkpoint lands, the second finds the disk full
            raise OSError(code, os.strerror(code))
        return real_save(self, name, **kw)

    monkeypatch.setattr(ck.CheckpointManager, "save", full_disk)
    out = tmp_path / "full"
    rc = botorl_main(["run", "--task", "pointmaze-umaze", "--profile", "smoke", "--no-progress", "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert words in err and str(out) in err
    s = json.loads((out / "summary.json").read_text())
    assert s["status"] == "failed" and words in s["error"]


def test_tensorboard_io_error_turns_tb_off(tmp_path, capsys):
    """An I/O error in the TensorBoard writer warns once and never blocks (the old writer thread hung)."""
    from botorl.pipeline.rundir import TBWriter

    tb = TBWriter(tmp_path / "tb", flush_secs=0.0)
    tb.add_scalar("x/nan", float("nan"), 1)  # skipped, no "NaN or Inf" message
    tb.add_scalar("x/ok", 1.0, 1)

    class Full:  # the events file on a full disk: every write, flush and close fails
        def write(self, *data):
            raise OSError(errno.ENOSPC, "No space left on device")

        flush = close = write

    tb._file.close()
    tb._file = Full()
    t0 = time.perf_counter()
    for i in range(100):
        tb.add_scalar("x/ok", 1.0, i)
    tb.close()
    assert time.perf_counter() - t0 < 5
    err = capsys.readouterr().err
    assert err.count("TensorBoard logging") == 1 and "No space left" in err
    assert not tb.enabled


def _tb_events(folder: Path) -> list:
    """(tag, step, value) of every scalar in an events file (TFRecord framing, tensorboardX protos)."""
    import struct

    from tensorboardX.proto.event_pb2 import Event

    out = []
    for f in folder.iterdir():
        data = f.read_bytes()
        i = 0
        while i < len(data):
            (n,) = struct.unpack("Q", data[i:i + 8])
            ev = Event.FromString(data[i + 12:i + 12 + n])
            i += 12 + n + 4
            for v in ev.summary.value:
                out.append((v.tag, ev.step, v.simple_value))
    return out


def test_tensorboard_skips_non_finite(tmp_path):
    from botorl.pipeline.rundir import MetricsLogger, RunDir

    run = RunDir(tmp_path / "r")
    run.create()
    log = MetricsLogger(run, tensorboard=True)
    log.log("finetune", 5, {"train_success": float("nan"), "loss": 0.5, "q": float("inf")})
    log.close()
    assert _tb_events(run.tb) == [("finetune/loss", 5, 0.5)]


def test_report_on_empty_directory_exits_2(tmp_path, capsys):
    assert botorl_main(["report", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "no finished run" in err and str(tmp_path) in err
    assert not (tmp_path / "report").exists()

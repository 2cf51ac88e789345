"""Links lead nowhere and nothing is lost (issue 51): whatever links a run, sweep or report
directory holds -- a symbolic link or a hard link at a file botorl writes (locks and appended
logs included), a folder on the way that is a link -- botorl changes nothing outside the folder
it was given; a record it cannot read stops the command with exit 2 and stays as it was.

No training here: each writer is driven on its own, a sweep's trials are a one-line stand-in.
The property test over every such name is `test_rundir_hostile.py::test_property_links_*`."""

from __future__ import annotations

import json
import os
import shlex
import socket
import sys
import time
from pathlib import Path

import pytest

from botorl.cli import main as botorl_main
from botorl.errors import BotorlError

# a sweep trial: `run --config C --out DIR` or `resume DIR` -> DIR/summary.json says finished
STAND_IN = [sys.executable, "-c", "import json, sys, pathlib; a = sys.argv; "
            "out = pathlib.Path(a[a.index('--out') + 1] if '--out' in a else a[2]); "
            "(out / 'summary.json').write_text(json.dumps({'status': 'finished'}))"]


def _outside(tmp_path: Path) -> tuple[Path, Path]:
    """A folder outside every directory given to botorl, and a file in it."""
    outside = tmp_path / "outside"
    outside.mkdir()
    precious = outside / "precious.txt"
    precious.write_text("keep me\n")
    return outside, precious


def _state(folder: Path) -> dict[str, tuple[int, bytes]]:
    """Every file under ``folder``: its inode and bytes."""
    return {str(p.relative_to(folder)): (p.stat().st_ino, p.read_bytes())
            for p in sorted(folder.rglob("*")) if p.is_file() and not p.is_symlink()}


def test_links_in_a_run_directory_never_change_the_file_outside(tmp_path):
    """Hard links at the lock, the appended logs and the summary, symbolic links at TensorBoard's
    next events files: every writer of a run replaces the link by a file of its own."""
    from botorl.io import atomic_write_json
    from botorl.pipeline.rundir import EVAL_COLUMNS, CsvLog, MetricsLogger, RunDir, RunLock

    outside, precious = _outside(tmp_path)
    before = _state(outside)
    run = RunDir(tmp_path / "run")
    run.create()
    for name in (".lock", "eval.csv", "summary.json", "metrics/pretrain.csv", "metrics/pretrain.jsonl"):
        os.link(precious, run.root / name)
    run.tb.mkdir()
    now = int(time.time())
    for t in range(now - 2, now + 60):  # the names TensorBoard's events file takes in the next minute
        (run.tb / f"events.out.tfevents.{t:010d}.{socket.gethostname()}").symlink_to(precious)
    with RunLock(run.root):
        logger = MetricsLogger(run, tensorboard=True)
        logger.log("pretrain", 1, {"loss": 0.5})
        logger.close()
        CsvLog(run.eval_csv, EVAL_COLUMNS, root=run.root).append({"stage": "finetune", "env_step": 0, "success": 1.0})
        atomic_write_json(run.summary, {"status": "running"}, root=run.root)
        assert (run.root / ".lock").read_text() == f"{os.getpid()}\n"
    assert _state(outside) == before and precious.stat().st_nlink == 1  # every hard link replaced
    for name in ("eval.csv", "metrics/pretrain.csv", "metrics/pretrain.jsonl"):  # copies of their own, appended to
        assert (run.root / name).stat().st_nlink == 1 and (run.root / name).read_text().startswith("keep me\n")
    assert json.loads((run.metrics / "pretrain.jsonl").read_text().splitlines()[-1])["loss"] == 0.5
    events = [p for p in run.tb.iterdir() if not p.is_symlink()]
    assert len(events) == 1 and events[0].stat().st_size > 0


def test_a_linked_checkpoints_folder_is_refused_before_latest_json_is_repaired(tmp_path, capsys):
    """Issue 51: `resume` repaired `latest.json` in the folder a `checkpoints/` link points at."""
    from botorl.pipeline.checkpoint import CheckpointManager
    from test_rundir_hostile import _crafted_run

    outside, _ = _outside(tmp_path)
    ck = CheckpointManager(outside / "checkpoints")
    ck.save("pretrain-final", state={"stage": "pretrain", "stage_done": True, "done_stages": ["pretrain"]})
    (ck.root / "latest.json").write_text("{not json")  # latest() would fall back and rewrite it
    d = _crafted_run(tmp_path / "run")
    (d / "checkpoints").symlink_to(ck.root)
    before = _state(outside)
    for argv in (["resume", str(d), "--no-progress"], ["eval", str(d)]):
        assert botorl_main(argv) == 2
        err = capsys.readouterr().err
        assert "checkpoints is a symbolic link" in err and "Traceback" not in err, err
    assert _state(outside) == before


def test_report_writes_only_under_the_folder_it_was_given(tmp_path, capsys):
    """Issue 51: `botorl report DIR` wrote through `DIR/report` when that was a link; so did an
    `--out` inside DIR. An `--out` elsewhere is the user's own (a link there is honoured)."""
    outside, _ = _outside(tmp_path)
    d = tmp_path / "runs" / "run"
    d.mkdir(parents=True)
    (d / "summary.json").write_text(json.dumps({"task": "t", "method": "wsrl", "seed": 0, "status": "finished"}))
    (d / "config.json").write_text(json.dumps({"task": "t", "method": "wsrl", "seed": 0, "pretrain": "calql"}))
    (d / "eval.csv").write_text("stage,env_step,success\nfinetune,0,1\nfinetune,10000,0.5\n")
    (tmp_path / "runs" / "report").symlink_to(outside)
    before = _state(outside)
    for out in ([], ["--out", str(tmp_path / "runs" / "report" / "sub")]):  # the default, or named inside DIR
        assert botorl_main(["report", str(tmp_path / "runs"), *out]) == 2
        err = capsys.readouterr().err
        assert "report is a symbolic link" in err and "Traceback" not in err, err
    assert _state(outside) == before


def test_a_sweep_writes_nothing_through_its_links(tmp_path):
    """Hard links at `.sweep.lock` and a trial's log leave the file outside as it was, and the
    sweep finishes; a trial or method folder that is a link is exit 2 before anything is written."""
    from botorl.experiments.grid import build_grid
    from botorl.experiments.sweep import LOCKFILE, TRIAL_LOG, Sweep, SweepOptions

    outside, precious = _outside(tmp_path)
    before = _state(outside)
    grid = build_grid(tasks="t1", methods="wsrl", seeds="0,1")
    out = tmp_path / "sw"
    (out / "t1" / "wsrl" / "seed0").mkdir(parents=True)
    os.link(precious, out / LOCKFILE)
    os.link(precious, out / "t1" / "wsrl" / "seed0" / TRIAL_LOG)
    opts = dict(backend="sequential", command=STAND_IN, progress=False, max_retries=0)
    manifest = Sweep(grid, SweepOptions(out=out, **opts)).run()
    assert manifest["counts"] == {"finished": 2}
    assert _state(outside) == before and precious.stat().st_nlink == 1
    for link in ("t1/wsrl/seed1", "t1/wsrl"):  # a trial folder, a method folder
        out = tmp_path / link.replace("/", "-") / "sw"
        (out / link).parent.mkdir(parents=True)
        (out / link).symlink_to(outside, target_is_directory=True)
        with pytest.raises(BotorlError, match="is a symbolic link"):
            Sweep(grid, SweepOptions(out=out, **opts)).run()
        assert _state(outside) == before and sorted(p.name for p in outside.iterdir()) == ["precious.txt"]


def test_an_unreadable_sweep_json_is_left_as_it_was(tmp_path, capsys):
    """Issue 51: a `sweep.json` over its size limit was replaced by a fresh one, and the sweep's
    history with it. Now exit 2 naming it, the file untouched; moved aside, the sweep goes on."""
    from botorl.io import SWEEP_JSON_LIMIT

    out = tmp_path / "sw"
    out.mkdir()
    argv = ["sweep", "--out", str(out), "--tasks", "t1", "--methods", "wsrl", "--seeds", "0", "--backend",
            "sequential", "--trial-command", shlex.join(STAND_IN), "--max-retries", "0"]
    for planted in ("huge", "not json", "a list"):
        path = out / "sweep.json"
        if planted == "huge":
            with open(path, "wb") as f:
                f.write(b'{"invocations": [')
                f.truncate(SWEEP_JSON_LIMIT + 1)  # sparse: no disk used
        else:
            path.write_text("{oops" if planted == "not json" else "[1, 2]")
        before = (path.stat().st_ino, path.stat().st_size, path.stat().st_mtime_ns)
        t0 = time.monotonic()
        assert botorl_main(argv) == 2, planted
        err = capsys.readouterr().err
        assert "sweep.json cannot be read" in err and "leaves it as it was" in err and "Traceback" not in err, err
        assert (path.stat().st_ino, path.stat().st_size, path.stat().st_mtime_ns) == before
        assert time.monotonic() - t0 < 60
        path.unlink()
    assert botorl_main(argv) == 0  # control: with the record moved aside, the sweep runs

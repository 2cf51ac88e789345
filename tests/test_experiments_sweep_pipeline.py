"""botorl sweep with the real `botorl run` (smoke profile) under each backend.

Each trial is a separate Python process that imports JAX and compiles its updates (the
persistent compile cache of botorl.jaxsetup makes repeats cheaper), ~20-30 s on 2 cores. So
the full grid (2 methods x 2 seeds = 4 trials; the grid's own logic over tasks, methods,
seeds and alphas is tested without training in test_experiments_sweep_logic.py) runs once,
on the local backend, and is killed mid-grid and restarted; the sequential and Ray backends
get a 2-trial grid.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from botorl.experiments.cli import report_main, sweep_main
from botorl.experiments.backend_local import cmdline

COMMON = ["--profile", "smoke", "--no-progress"]


def sweep_args(out: Path, *, tasks="pointmaze-umaze", methods="boto,wsrl", seeds="0-1", backend="local", extra=()):
    return ["--tasks", tasks, "--methods", methods, "--seeds", seeds, "--out", str(out),
            "--backend", backend, *COMMON, *extra]


def finished_runs(out: Path) -> dict[Path, int]:
    """run dir -> mtime of its summary.json, for runs with status finished."""
    done = {}
    for p in out.rglob("summary.json"):
        try:
            if json.loads(p.read_text()).get("status") == "finished":
                done[p.parent] = p.stat().st_mtime_ns
        except (OSError, ValueError):
            pass  # being written
    return done


def attempts(run_dir: Path) -> int:
    return (run_dir / "sweep-trial.log").read_text().count("===== botorl sweep: attempt")


def _mentions(pid: int, needle: str) -> bool:
    """The command line or an open file of `pid` contains `needle` (Ray's daemons rename
    their process title, but keep their log files under the instance's temp dir open)."""
    if needle in cmdline(pid):
        return True
    try:
        fds = list(Path(f"/proc/{pid}/fd").iterdir())
    except OSError:
        return False
    for fd in fds:
        try:
            if needle in os.readlink(fd):
                return True
        except OSError:
            continue
    return False


def processes_in(out: Path) -> list[int]:
    me = os.getpid()
    return [int(p.name) for p in Path("/proc").iterdir()
            if p.name.isdigit() and int(p.name) != me and _mentions(int(p.name), str(out))]


# slow (~3 min): test_experiments_sweep_logic kills a sweep's process group and completes it with the
# same command, and test_study kills a study mid-arm and resumes it, in the default suite
@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_local_full_grid_killed_and_restarted(tmp_path):
    """4 real trials, 2 pinned workers; SIGKILL only the sweep process mid-grid (its trials
    must not live on as orphans); the same command again completes the grid and reruns no
    finished trial."""
    out = tmp_path / "sweep"
    grid = sweep_args(out, extra=["--workers", "2"])
    cmd = [sys.executable, "-m", "botorl.cli", "sweep", *grid]
    log = open(tmp_path / "first.log", "wb")
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and len(finished_runs(out)) < 2 and proc.poll() is None:
        time.sleep(0.2)
    assert proc.poll() is None, (tmp_path / "first.log").read_text()[-3000:]
    # the manifest says which cores the running trials were pinned to
    manifest = json.loads((out / "sweep.json").read_text())
    cpus = {e.get("cpu") for e in manifest["trials"].values() if e["state"] == "running"}
    assert cpus and None not in cpus and cpus <= set(os.sched_getaffinity(0))
    os.kill(proc.pid, signal.SIGKILL)  # only the parent: the trials get PR_SET_PDEATHSIG
    proc.wait()
    before = finished_runs(out)
    assert 2 <= len(before) < 4
    deadline = time.monotonic() + 20
    while processes_in(out) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert processes_in(out) == [], "trial processes outlived the killed sweep"

    assert sweep_main(grid) == 0
    after = finished_runs(out)
    assert len(after) == 4
    for run_dir, mtime in before.items():
        assert after[run_dir] == mtime, f"{run_dir} was rerun"
        assert attempts(run_dir) == 1
    manifest = json.loads((out / "sweep.json").read_text())
    assert manifest["counts"] == {"finished": 4}
    assert len(manifest["invocations"]) == 2
    for entry in manifest["trials"].values():
        run_dir = out / entry["dir"]
        config = json.loads((run_dir / "config.json").read_text())
        assert (config["task"], config["method"], config["seed"], config["profile"]) == (
            entry["task"], entry["method"], entry["seed"], "smoke")
    # the report reads the sweep: 2 groups of 2 seeds, no 10k point in a 40-step smoke run
    rep = tmp_path / "report"
    assert report_main([str(out), "--out", str(rep), "--bootstrap", "50"]) == 0
    table = (rep / "table1.csv").read_text().splitlines()
    assert len(table) == 1 + 2 and all(",0 1," in row for row in table[1:])
    assert (rep / "figure5.png").stat().st_size > 10_000


@pytest.mark.timeout(600)
def test_sequential_backend(tmp_path):
    out = tmp_path / "seq"
    assert sweep_main(sweep_args(out, tasks="pointmaze-umaze", methods="wsrl,boto", seeds="0",
                                 backend="sequential", extra=["--alphas", "0.5"])) == 0
    done = finished_runs(out)
    assert sorted(p.relative_to(out).as_posix() for p in done) == [
        "pointmaze-umaze/boto/alpha+0.50/seed0", "pointmaze-umaze/wsrl/seed0"]
    summary = json.loads((out / "pointmaze-umaze/boto/alpha+0.50/seed0/summary.json").read_text())
    assert summary["alpha"] == 0.5 and summary["profile"] == "smoke"
    # BOTO ran second and started from WSRL's pre-training of seed 0 (the same Cal-QL settings)
    boto, wsrl = out / "pointmaze-umaze/boto/alpha+0.50/seed0", out / "pointmaze-umaze/wsrl/seed0"
    assert json.loads((boto / "config.json").read_text())["pretrained"] == str(out.resolve())
    assert json.loads((wsrl / "config.json").read_text())["pretrained"] is None
    assert (boto / "metrics/pretrain.csv").read_text() == (wsrl / "metrics/pretrain.csv").read_text()
    manifest = json.loads((out / "sweep.json").read_text())
    first, second = sorted(manifest["trials"].values(), key=lambda e: e["started"])
    assert first["ended"] <= second["started"]  # one at a time
    assert first["cpu"] is None and second["cpu"] is None  # not pinned


# slow (~75 s, most of it Ray starting): Ray is an optional extra; test_sequential_backend runs the
# same grid through the backend interface in the default suite
@pytest.mark.slow
@pytest.mark.timeout(600)
def test_ray_backend(tmp_path):
    pytest.importorskip("ray", reason="the ray backend needs `pip install 'botorl[ray]'`")
    out = tmp_path / "ray"
    assert sweep_main(sweep_args(out, tasks="pointmaze-medium", seeds="0", backend="ray",
                                 extra=["--workers", "2"])) == 0
    assert len(finished_runs(out)) == 2
    manifest = json.loads((out / "sweep.json").read_text())
    assert manifest["counts"] == {"finished": 2}
    assert "ray_local_temp_dir" not in manifest  # the local instance was shut down
    assert processes_in(out) == []
    # the sweep's token went to Ray's daemons only: a child this process starts later is no
    # process of the sweep's (test_rundir_hostile's bystander failed after this test before)
    from botorl.experiments.backend_local import TOKEN_ENV

    assert TOKEN_ENV not in os.environ

"""botorl sweep's bookkeeping with a stand-in trial command (fast, no JAX): retries resume
from the checkpoint, user errors are not retried, one sweep per directory, a killed sweep
process group is finished by the same command without rerunning finished trials.

The real `botorl run` under every backend is tested in test_experiments_sweep_pipeline.py.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import pytest

from botorl.errors import BotorlError
from botorl.experiments.cli import sweep_main
from botorl.experiments.grid import build_grid
from botorl.experiments.sweep import Sweep, SweepOptions, next_action

# Speaks the `botorl run --config FILE --out DIR` / `botorl resume DIR` protocol of CONTRACTS.md "Runs"
# (FILE: the trial's config, here the grid's fields of a task botorl does not know).
FAKE = textwrap.dedent(
    """
    import json, os, sys, time
    from pathlib import Path
    argv = [a for a in sys.argv[1:] if a != "--no-progress"]
    if argv[0] == "run":
        toks = []
        for t in argv[1:]:
            toks += t.split("=", 1) if t.startswith("--") and "=" in t else [t]
        a = dict(zip(toks[0::2], toks[1::2]))
        out = Path(a["--out"])
        out.mkdir(parents=True, exist_ok=True)
        given = json.loads(Path(a["--config"]).read_text())
        cfg = {k: given[k] for k in ("task", "method", "seed", "alpha", "pretrain")}
        (out / "config.json").write_text(json.dumps(cfg))
        start_at = 0
    else:
        out = Path(argv[1])
        cfg = json.loads((out / "config.json").read_text())
        ckpt = out / "checkpoints" / "step"
        start_at = int(ckpt.read_text()) if ckpt.exists() else 0
    with open(out / "starts.txt", "a") as f:
        f.write(argv[0] + "\\n")
    (out / "worker.json").write_text(json.dumps({"cpus": sorted(os.sched_getaffinity(0)),
        "omp": os.environ.get("OMP_NUM_THREADS"), "openblas": os.environ.get("OPENBLAS_NUM_THREADS")}))
    if os.environ.get("FAKE_EXIT"):
        sys.exit(int(os.environ["FAKE_EXIT"]))
    (out / "summary.json").write_text(json.dumps({**cfg, "status": "running"}))
    for step in range(start_at, 4):
        time.sleep(float(os.environ.get("FAKE_SLEEP", "0.05")))
        (out / "checkpoints").mkdir(exist_ok=True)
        (out / "checkpoints" / "step").write_text(str(step + 1))
        if os.environ.get("FAKE_FAIL_ONCE") and step == 1 and argv[0] == "run":
            sys.exit(1)
    (out / "eval.csv").write_text("stage,env_step,success,return,q_data,q_uniform\\nonline,0,0.5,0,0,0\\n")
    (out / "summary.json").write_text(json.dumps({**cfg, "status": "finished", "success_initial": 0.5,
        "success_10k": None, "success_final": 0.5, "stage_seconds": {}}))
    """
)


@pytest.fixture()
def fake(tmp_path) -> list[str]:
    path = tmp_path / "fake_botorl.py"
    path.write_text(FAKE)
    return [sys.executable, str(path)]


def starts(run_dir: Path) -> list[str]:
    return (run_dir / "starts.txt").read_text().split()


def test_failed_trial_resumes_from_checkpoint(tmp_path, fake, monkeypatch):
    monkeypatch.setenv("FAKE_FAIL_ONCE", "1")
    grid = build_grid(tasks="t1", methods="boto,wsrl", seeds="0", alphas="0.5")
    sweep = Sweep(grid, SweepOptions(out=tmp_path / "sw", backend="sequential", command=fake, progress=False))
    manifest = sweep.run()
    for trial in sweep.trials:
        d = sweep.run_dir(trial)
        assert starts(d) == ["run", "resume"]  # the retry continued from the checkpoint
        entry = manifest["trials"][trial.relpath]
        assert entry["state"] == "finished" and entry["launches"] == 2
        assert next_action(d) == "done"
        assert (d / "sweep-trial.log").read_text().count("===== botorl sweep: attempt") == 2
    saved = json.loads((tmp_path / "sw" / "sweep.json").read_text())
    assert saved["counts"] == {"finished": 2}
    assert saved["trials"]["t1/boto/alpha+0.50/seed0"]["alpha"] == 0.5
    assert saved["trials"]["t1/wsrl/seed0"]["alpha"] is None
    # a finished grid is never rerun
    Sweep(grid, SweepOptions(out=tmp_path / "sw", backend="local", command=fake, progress=False)).run()
    assert all(starts(sweep.run_dir(t)) == ["run", "resume"] for t in sweep.trials)
    # other settings in the same directory would mix runs silently: refused
    other = build_grid(tasks="t1", methods="boto,wsrl", seeds="0", alphas="0.5", profile="full")
    with pytest.raises(BotorlError, match="profile"):
        Sweep(other, SweepOptions(out=tmp_path / "sw", command=fake, progress=False)).run()
    # more seeds are fine: only the new trials run
    more = build_grid(tasks="t1", methods="boto,wsrl", seeds="0-1", alphas="0.5")
    manifest = Sweep(more, SweepOptions(out=tmp_path / "sw", command=fake, progress=False)).run()
    assert manifest["counts"] == {"finished": 4}
    assert all(starts(sweep.run_dir(t)) == ["run", "resume"] for t in sweep.trials)


def test_retry_limit_and_user_errors(tmp_path, fake, monkeypatch, capsys):
    out = tmp_path / "sw"
    args = ["--tasks", "t1", "--methods", "wsrl", "--seeds", "0", "--out", str(out),
            "--trial-command", " ".join(fake), "--no-progress", "--backend", "sequential"]
    monkeypatch.setenv("FAKE_EXIT", "1")
    assert sweep_main(args + ["--max-retries", "1"]) == 1
    assert len(starts(out / "t1/wsrl/seed0")) == 2  # 1 + max_retries launches
    assert "FAILED t1/wsrl/seed0: exited with code 1" in capsys.readouterr().err
    monkeypatch.setenv("FAKE_EXIT", "2")  # BotorlError: a retry cannot help
    assert sweep_main(args) == 2  # every failed trial refused its input: the sweep's exit 2 too (issue 51)
    assert len(starts(out / "t1/wsrl/seed0")) == 3
    monkeypatch.delenv("FAKE_EXIT")
    assert sweep_main(args) == 0  # the same command again retries the failed trial
    manifest = json.loads((out / "sweep.json").read_text())
    assert manifest["trials"]["t1/wsrl/seed0"]["state"] == "finished"
    assert len(manifest["invocations"]) == 3


def test_one_sweep_per_directory(tmp_path, fake):
    import fcntl

    out = tmp_path / "sw"
    out.mkdir()
    with open(out / ".sweep.lock", "w") as holder:
        fcntl.flock(holder, fcntl.LOCK_EX)
        holder.write("pid 1 on elsewhere")
        holder.flush()
        sweep = Sweep(build_grid(tasks="t1", methods="wsrl", seeds="0"),
                      SweepOptions(out=out, backend="sequential", command=fake, progress=False))
        with pytest.raises(BotorlError, match="Another sweep"):
            sweep.run()


def test_killed_process_group_then_same_command_completes(tmp_path, fake):
    out = tmp_path / "sw"
    cmd = [sys.executable, "-m", "botorl.cli", "sweep", "--tasks", "t1,t2", "--methods", "boto,wsrl",
           "--seeds", "0-1", "--out", str(out), "--backend", "local", "--workers", "2",
           "--trial-command", " ".join(fake), "--no-progress"]
    env = dict(os.environ, FAKE_SLEEP="0.4")
    proc = subprocess.Popen(cmd, env=env, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    finished_before: dict[Path, float] = {}
    while time.monotonic() < deadline:
        done = [p.parent for p in out.glob("*/*/**/summary.json")
                if json.loads(p.read_text() or "{}").get("status") == "finished"]
        if len(done) >= 2:
            break
        time.sleep(0.1)
    os.killpg(proc.pid, signal.SIGKILL)  # the sweep and its trials, as a Ctrl-\ or OOM would
    proc.wait()
    for d in (p.parent for p in out.glob("*/*/**/summary.json")):
        if json.loads((d / "summary.json").read_text()).get("status") == "finished":
            finished_before[d] = (d / "summary.json").stat().st_mtime_ns
    assert 2 <= len(finished_before) < 8, "kill the sweep mid-grid"
    subprocess.run(cmd, env=dict(os.environ, FAKE_SLEEP="0.01"), check=True, timeout=120,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    manifest = json.loads((out / "sweep.json").read_text())
    assert manifest["counts"] == {"finished": 8}
    for d, mtime in finished_before.items():
        assert (d / "summary.json").stat().st_mtime_ns == mtime
        assert len(starts(d)) == 1, f"{d} was rerun"
    relaunched = [t for t, e in manifest["trials"].items() if e["launches"] > 1]
    assert all(out / t not in finished_before for t in relaunched)


def test_sigterm_stops_trials_and_records_them(tmp_path, fake):
    out = tmp_path / "sw"
    cmd = [sys.executable, "-m", "botorl.cli", "sweep", "--tasks", "t1", "--methods", "wsrl",
           "--seeds", "0-1", "--out", str(out), "--backend", "local", "--workers", "2",
           "--trial-command", " ".join(fake), "--no-progress"]
    proc = subprocess.Popen(cmd, env=dict(os.environ, FAKE_SLEEP="5"), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and len(list(out.glob("t1/wsrl/seed*/starts.txt"))) < 2:
        time.sleep(0.1)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=30) == 128 + signal.SIGTERM
    manifest = json.loads((out / "sweep.json").read_text())
    assert {e["state"] for e in manifest["trials"].values()} == {"interrupted"}
    pids = [e.get("pid") for e in manifest["trials"].values()]
    assert pids == [None, None]
    for d in out.glob("t1/wsrl/seed*"):
        assert not (d / ".sweep-trial.json").exists() or not _alive_from(d)


def _alive_from(run_dir: Path) -> bool:
    info = json.loads((run_dir / ".sweep-trial.json").read_text())
    try:
        os.kill(info["pid"], 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{info['pid']}/status").read_text().find("State:\tZ") < 0


def test_local_workers_are_pinned_single_threaded(tmp_path, fake):
    cores = sorted(os.sched_getaffinity(0))
    grid = build_grid(tasks="t1", methods="wsrl", seeds=f"0-{len(cores)}")  # one more than cores
    sweep = Sweep(grid, SweepOptions(out=tmp_path / "loc", backend="local", command=fake, progress=False))
    manifest = sweep.run()
    used = []
    for trial in sweep.trials:
        worker = json.loads((sweep.run_dir(trial) / "worker.json").read_text())
        assert len(worker["cpus"]) == 1 and worker["cpus"][0] in cores
        assert worker["omp"] == "1" and worker["openblas"] == "1"
        assert [manifest["trials"][trial.relpath]["cpu"]] == worker["cpus"]
        used += worker["cpus"]
    assert set(used) == set(cores)  # every core got work
    seq = Sweep(build_grid(tasks="t1", methods="wsrl", seeds="0"),
                SweepOptions(out=tmp_path / "seq", backend="sequential", command=fake, progress=False))
    seq.run()
    worker = json.loads((seq.run_dir(seq.trials[0]) / "worker.json").read_text())
    assert worker["cpus"] == cores  # the sequential backend leaves the whole machine to its trial


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs at least 2 cores")
def test_fewer_workers_than_cores_get_blocks_of_cores(tmp_path, fake):
    """One worker on a C-core machine gets all C cores and its thread pools (pinning it to one
    core, as before, left the others idle)."""
    cores = sorted(os.sched_getaffinity(0))
    sweep = Sweep(build_grid(tasks="t1", methods="wsrl", seeds="0-1"),
                  SweepOptions(out=tmp_path / "one", backend="local", workers=1, command=fake, progress=False))
    manifest = sweep.run()
    for trial in sweep.trials:
        worker = json.loads((sweep.run_dir(trial) / "worker.json").read_text())
        assert worker["cpus"] == cores and worker["omp"] is None
        assert manifest["trials"][trial.relpath]["cpus"] == cores and manifest["trials"][trial.relpath]["cpu"] is None
    # two workers, two trials launched together (slots 0 and 1): disjoint blocks covering every core
    sweep = Sweep(build_grid(tasks="t1", methods="wsrl", seeds="0-1"),
                  SweepOptions(out=tmp_path / "two", backend="local", workers=2, command=fake, progress=False))
    sweep.run()
    blocks = [json.loads((sweep.run_dir(t) / "worker.json").read_text())["cpus"] for t in sweep.trials]
    assert sorted(c for b in blocks for c in b) == cores


def test_trials_start_without_forking_the_sweep(tmp_path, fake, monkeypatch):
    """The sweep process may hold JAX's threads (it builds each trial's config); a trial starts
    by spawn + exec of the launcher (botorl.experiments.child), which pins and arms the
    parent-death signal itself: no os.fork of the sweep, no Python run in a forked child."""
    import jax.numpy as jnp

    jnp.zeros(1).block_until_ready()  # JAX's backend threads are up, as in a sweep that built configs
    seen = []
    real = subprocess.Popen.__init__

    def spy(self, args, *a, **kw):
        seen.append((list(args), kw.get("preexec_fn")))
        real(self, args, *a, **kw)

    monkeypatch.setattr(subprocess.Popen, "__init__", spy)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # JAX warns (RuntimeWarning) when os.fork() runs under it
        Sweep(build_grid(tasks="t1", methods="wsrl", seeds="0-1"),
              SweepOptions(out=tmp_path / "sw", backend="local", workers=1, command=fake, progress=False)).run()
    assert len(seen) == 2 and all(pre is None for _, pre in seen)
    assert all(cmd[1:3] == ["-m", "botorl.experiments.child"] and cmd[cmd.index("--") + 1:][:2] == fake
               for cmd, _ in seen)


def test_ray_backend_without_ray_is_a_clear_error(tmp_path, fake, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    sweep = Sweep(build_grid(tasks="t1", methods="wsrl", seeds="0"),
                  SweepOptions(out=tmp_path / "sw", backend="ray", command=fake, progress=False))
    with pytest.raises(BotorlError, match=r"pip install 'botorl\[ray\]'"):
        sweep.run()
    assert json.loads((tmp_path / "sw" / "sweep.json").read_text())["counts"] == {"pending": 1}


def test_orphan_of_an_earlier_sweep_is_stopped(tmp_path):
    from botorl.experiments.sweep import TRIAL_PID, stop_orphan
    from botorl.io import atomic_write_json as write_json_atomic

    run_dir = tmp_path / "t1" / "wsrl" / "seed0"
    run_dir.mkdir(parents=True)
    sleeper = [sys.executable, "-c", "import time; time.sleep(120)"]
    from botorl.experiments.backend_local import TOKEN_ENV, sweep_token

    token = sweep_token(tmp_path)  # the orphan was started by a sweep of tmp_path: it carries its token (issue 39)
    orphan = subprocess.Popen(sleeper + [str(run_dir.resolve())], env={**os.environ, TOKEN_ENV: token})
    stranger = subprocess.Popen(sleeper + ["unrelated"])
    bystander = subprocess.Popen(sleeper + [str(run_dir.resolve())])  # works on the directory, no sweep started it
    try:
        import socket

        from botorl.experiments.backend_local import start_time

        host = socket.gethostname()
        # pid, start time and this directory in its command line: still no proof a sweep started it
        for tok in (None, token, "0" * 32):
            write_json_atomic(run_dir / TRIAL_PID, {"pid": bystander.pid, "start": start_time(bystander.pid),
                                                    "host": host, "token": tok})
            assert not stop_orphan(run_dir, tmp_path)
        assert bystander.poll() is None
        write_json_atomic(run_dir / TRIAL_PID, {"pid": stranger.pid, "start": start_time(stranger.pid), "host": host})
        assert not stop_orphan(run_dir, tmp_path)  # a pid that is not this trial's is never touched
        assert stranger.poll() is None
        # the trial's pid with another start time: the pid of a process that ended, reused
        write_json_atomic(run_dir / TRIAL_PID, {"pid": orphan.pid, "start": start_time(orphan.pid) - 1, "host": host})
        assert not stop_orphan(run_dir, tmp_path)
        write_json_atomic(run_dir / TRIAL_PID, {"pid": orphan.pid, "host": host})  # no start time: not a record
        assert not stop_orphan(run_dir, tmp_path)
        assert orphan.poll() is None
        write_json_atomic(run_dir / TRIAL_PID, {"pid": orphan.pid, "start": start_time(orphan.pid), "host": host})
        assert not stop_orphan(run_dir, tmp_path)  # no token recorded
        write_json_atomic(run_dir / TRIAL_PID, {"pid": orphan.pid, "start": start_time(orphan.pid), "host": host,
                                                "token": token})
        assert stop_orphan(run_dir, tmp_path)
        assert orphan.wait(timeout=20) == -signal.SIGTERM
    finally:
        for p in (orphan, stranger, bystander):
            if p.poll() is None:
                p.kill()
                p.wait()


def test_relative_pretrained_is_made_absolute_when_the_sweep_starts(tmp_path, monkeypatch):
    """`botorl sweep --set pretrained=study/x`: trials run in the sweep's folder, so the path is
    resolved against the folder the sweep starts in, and a missing one is refused there (issue 42)."""
    from botorl.errors import ConfigError

    monkeypatch.chdir(tmp_path)
    (tmp_path / "study" / "x").mkdir(parents=True)
    grid = build_grid(tasks="pointmaze-umaze", methods="wsrl", seeds="0", profile="smoke",
                      overrides=["pretrained=study/x", "data.path=not-a-file-but-a-minari-id"])
    assert grid.overrides["pretrained"] == str(tmp_path / "study" / "x")
    assert grid.overrides["data.path"] == "not-a-file-but-a-minari-id"  # a name, not a path: kept
    monkeypatch.chdir("/")  # the trial's own folder does not matter any more
    assert grid.config(grid.trials()[0]).pretrained == str(tmp_path / "study" / "x")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match="pretrained=study/y: no such directory"):
        build_grid(tasks="pointmaze-umaze", methods="wsrl", seeds="0", overrides=["pretrained=study/y"])


def test_a_bystander_listed_in_sweep_json_survives_the_sweep(tmp_path, fake):
    """Issue 39: sweep.json's ``ray_local_processes`` (and a trial's pid file) listing a live process
    of this user's with its real start time, whatever the backend: the sweep stops nothing it did
    not start (the process carries no token of a sweep)."""
    import socket

    from botorl.experiments.backend_local import TRIAL_PID, start_time

    bystander = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    try:
        out = tmp_path / "sw"
        out.mkdir()
        rec = {"pid": bystander.pid, "start": start_time(bystander.pid)}
        (out / "sweep.json").write_text(json.dumps({"ray_local_processes": [rec, {**rec, "token": "f" * 32}]}))
        run_dir = out / "t1" / "wsrl" / "seed0"
        run_dir.mkdir(parents=True)
        (run_dir / TRIAL_PID).write_text(json.dumps({**rec, "host": socket.gethostname(), "token": "f" * 32}))
        grid = build_grid(tasks="t1", methods="wsrl", seeds="0")
        Sweep(grid, SweepOptions(out=out, backend="sequential", command=fake, progress=False)).run()
        assert json.loads((run_dir / "summary.json").read_text())["status"] == "finished"
        assert bystander.poll() is None
    finally:
        bystander.kill()
        bystander.wait()

"""SIGTERM / SIGINT (a scheduler's preemption, Ctrl-C): a checkpoint at the current step, status
``interrupted``, how to resume, exit 143 / 130 within seconds; the resume ends exactly where
an uninterrupted run ends.

Each case runs the real CLI in a subprocess and sends it a real signal while a chosen stage
runs: ``BOTORL_PAUSE_AT=STAGE:STEP`` (botorl/pipeline/faults.py) makes the run create a file
when STAGE reaches STEP and wait while it exists, so the signal lands at a known step of that
stage (steps that are not checkpoint points, so the checkpoint is the interrupt's own). The
test sends the signal, then removes the file; the time from the signal to the exit is
measured. One uninterrupted run per module is the reference (test_reliability_resume.ARGS:
pre-training 40 steps, warm-up 30 env steps, BOTO 30 steps, fine-tuning 30 to 80, periodic
checkpoints every 10); equal is that module's ``assert_same_run`` (eval.csv byte for byte,
summary, every metrics row, the final agent file).
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

from botorl.cli import main as botorl_main
from test_reliability_resume import ARGS, REPO, assert_same_run

TASK = "pointmaze-umaze"
EXIT_S = 30.0  # the bound; measured: about 1 s on a loaded 2-core CPU


def _env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("BOTORL_KILL", "BOTORL_PAUSE"))}
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.update(extra)
    return env


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("preempt") / "reference"
    assert botorl_main(["run", "--task", TASK, *ARGS, "--out", str(out)]) == 0
    return out


def _paused(args: list[str], at: str, pause: Path) -> subprocess.Popen:
    """`botorl ARGS` that waits at ``at`` (STAGE:STEP) while ``pause`` exists."""
    proc = subprocess.Popen([sys.executable, "-m", "botorl.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            env=_env(BOTORL_PAUSE_AT=at, BOTORL_PAUSE_FILE=str(pause)))
    deadline = time.monotonic() + 300
    while not pause.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise AssertionError(f"the run never reached {at}: rc {proc.poll()}\n{proc.communicate()[1][-3000:]}")
        time.sleep(0.02)
    return proc


def _signal(proc: subprocess.Popen, sigs: list[int], pause: Path | None) -> tuple[int, float, str]:
    """Send ``sigs`` (in a burst), release the pause; (exit code, seconds from the first signal, stderr)."""
    t0 = time.monotonic()
    for s in sigs:
        proc.send_signal(s)
    if pause is not None:
        pause.unlink()
    try:
        _, err = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    return proc.returncode, time.monotonic() - t0, err


def _status(d: Path) -> str:
    return json.loads((d / "summary.json").read_text())["status"]


def _latest(d: Path) -> dict:
    return json.loads((d / "checkpoints" / "latest.json").read_text())


def _resume(d: Path, capsys) -> str:
    capsys.readouterr()
    assert botorl_main(["resume", str(d), "--no-progress"]) == 0
    return capsys.readouterr().err


# stage, the step the signal lands at, the signal, the checkpoint the resume starts from
CASES = [
    ("pretrain", 15, signal.SIGTERM, "pretrain-step000000015"),
    ("warmup", 12, signal.SIGTERM, "pretrain-final"),  # no mid-warm-up checkpoint: it starts again (exact)
    ("boto", 15, signal.SIGTERM, "boto-step000000015"),
    # SIGINT takes SIGTERM's path (one handler for both, botorl/pipeline/preempt.py); mid log
    # window: its metrics are saved too
    ("finetune", 55, signal.SIGINT, "finetune-step000000055"),
]
# slow (~15 s each): the default suite signals the first and the last stage, and SIGTERM and SIGINT
SLOW_STAGES = ("warmup", "boto")


@pytest.mark.parametrize("stage, step, sig, ckpt", [
    pytest.param(*c, id=f"{c[0]}-{c[2].name}", marks=[pytest.mark.slow] if c[0] in SLOW_STAGES else [])
    for c in CASES])
def test_signal_in_stage_checkpoints_and_resumes_exactly(reference, tmp_path, capsys, stage, step, sig, ckpt):
    out, pause = tmp_path / "run", tmp_path / "pause"
    proc = _paused(["run", "--task", TASK, *ARGS, "--out", str(out)], f"{stage}:{step}", pause)
    # SIGINT twice in a burst (Ctrl-C reaches a whole process group; a sweep forwards it too):
    # one preemption, not the "second signal" that exits at once
    rc, secs, err = _signal(proc, [sig, sig] if sig == signal.SIGINT else [sig], pause)
    print(f"{stage} {sig.name}: exit {rc} after {secs:.2f} s")
    assert rc == 128 + sig, err[-3000:]
    assert secs < EXIT_S
    assert _status(out) == "interrupted"
    assert _latest(out)["name"] == ckpt
    assert f"Continue with: botorl resume {out}" in err and f"checkpoint {ckpt}" in err
    err = _resume(out, capsys)
    assert f"(checkpoint {ckpt})" in err
    assert_same_run(reference, out, f"{sig.name} in {stage} at step {step}")


def test_second_signal_exits_at_once(reference, tmp_path, capsys):
    """A second signal (after the first has been taken) exits at once: no checkpoint of the
    current step, the last complete one kept, status still ``running``; the resume is exact."""
    out, pause = tmp_path / "run", tmp_path / "pause"
    proc = _paused(["run", "--task", TASK, *ARGS, "--out", str(out)], "finetune:55", pause)
    proc.send_signal(signal.SIGTERM)
    time.sleep(1.5)  # past preempt.DUPLICATE_S: a second request, not a copy of the first
    rc, secs, err = _signal(proc, [signal.SIGTERM], None)  # the pause is never released
    assert rc == 143 and secs < 5, err[-3000:]
    assert "SIGTERM again: exiting now" in err
    assert _status(out) == "running"
    assert _latest(out)["name"] == "finetune-step000000050"  # the periodic one before the pause
    pause.unlink()
    _resume(out, capsys)
    assert_same_run(reference, out, "second SIGTERM")


def test_signal_before_training_leaves_nothing_to_resume(tmp_path):
    """A signal while the run is still being set up (before the run directory exists) exits 143
    at once and says there is nothing to resume."""
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-c", "import os, signal, sys; from botorl.cli import main; "
                             "import botorl.pipeline.runner as r; "
                             "r.load_offline = lambda *a: os.kill(os.getpid(), signal.SIGTERM); "
                             f"sys.exit(main(['run', '--task', '{TASK}', '--profile', 'smoke', '--out', '{out}']))"],
                            env=_env(), stderr=subprocess.PIPE, text=True)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 143, err[-3000:]
    assert "stopped by SIGTERM before any work was saved" in err
    assert not out.exists()


@pytest.mark.slow
@pytest.mark.timeout(900)  # a population run to the end, and one signalled and resumed
def test_population_signal_resumes_exactly(tmp_path, capsys):
    """A population of two hit by SIGTERM in fine-tuning: one checkpoint of the population at
    that step, every member and population.json ``interrupted``; resumed, every member ends as
    in an uninterrupted population."""
    ref, out, pause = tmp_path / "ref", tmp_path / "pop", tmp_path / "pause"
    pop = ["--task", TASK, *ARGS, "--seeds", "0,1"]
    assert botorl_main(["run", *pop, "--out", str(ref)]) == 0
    proc = _paused(["run", *pop, "--out", str(out)], "finetune:55", pause)
    rc, secs, err = _signal(proc, [signal.SIGTERM], pause)
    assert rc == 143 and secs < EXIT_S, err[-3000:]
    data = json.loads((out / "population.json").read_text())
    assert data["status"] == "interrupted" and {m["status"] for m in data["members"]} == {"interrupted"}
    assert _latest(out)["name"] == "finetune-step000000055"
    assert f"Continue with: botorl resume {out}" in err
    _resume(out, capsys)
    # eval.csv exactly. (Not the metrics rows and the agent file: after any resume of a
    # population, SIGKILL's too, its last actor_loss row differs in the 7th digit and so does
    # the final agent -- test_reliability_resume.test_population_resumes_exactly fails the same
    # way on the code before preemption; a known problem of its own.)
    for m in ("seed0", "seed1"):
        assert (out / m / "eval.csv").read_text() == (ref / m / "eval.csv").read_text(), m
        assert _status(out / m) == "finished"


@pytest.mark.slow  # ~26 s; tests/test_experiments_sweep_logic.py checks the sweep's part with a stand-in trial
def test_sweep_sigterm_stops_its_trial_with_a_checkpoint_and_resumes_it(reference, tmp_path):
    """`botorl sweep` hit by SIGTERM forwards it to its running trial, which checkpoints at its
    step and exits 143; the sweep records the trial ``interrupted`` and exits 143. The same
    command again resumes the trial from that checkpoint to the uninterrupted run's numbers."""
    out, pause = tmp_path / "sweep", tmp_path / "pause"
    sets = ["offline.steps=40", "boto.boto_steps=30", "online.steps=80", "checkpoint_every=10", "eval.interval=20"]
    cmd = ["sweep", "--tasks", TASK, "--methods", "boto", "--seeds", "0", "--profile", "smoke", "--set", *sets,
           "--backend", "sequential", "--out", str(out), "--no-progress"]
    proc = _paused(cmd, "finetune:55", pause)
    rc, secs, err = _signal(proc, [signal.SIGTERM], pause)
    assert rc == 143 and secs < EXIT_S, err[-3000:]
    manifest = json.loads((out / "sweep.json").read_text())
    (entry,) = manifest["trials"].values()
    assert entry["state"] == "interrupted"
    trial = out / entry["dir"]
    assert _status(trial) == "interrupted" and _latest(trial)["name"] == "finetune-step000000055"
    res = subprocess.run([sys.executable, "-m", "botorl.cli", *cmd], env=_env(), capture_output=True, text=True,
                         timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "from finetune step 55" in (trial / "sweep-trial.log").read_text()
    assert_same_run(reference, trial, "sweep trial stopped by SIGTERM")

"""Exact resume: a run killed anywhere and resumed ends exactly where an uninterrupted one ends.

For each env family (pointmaze-umaze; door-binary-local, data made from the shipped demos;
antmaze and kitchen through the small Minari files test_pipeline_tasks.py writes, the only
data of theirs a test may have) one uninterrupted smoke run is the reference. Kill points:
a seeded random step in each stage (pre-training, warm-up, BOTO, fine-tuning; printed, and
named in every failure; ``BOTORL_KILL_SEED`` picks others), the inside of the checkpoint
writer (after the agent file, before the rest; after the rename, before latest.json), and
a corrupted newest checkpoint. Two ways to kill:

* in-process (fast): botorl.pipeline.faults calls a hook at the end of every step and at the
  checkpoint writer's phases; the hook copies the run directory there, which is what a
  kill -9 at that point leaves on disk (every write before it has completed, the logs are
  appended and flushed line by line, checkpoints are written whole or not at all). The copy
  is then resumed with ``botorl resume``. The reference run takes every copy, so one
  reference serves all kill points of its family.
* real SIGKILL (subprocesses of the CLI): ``BOTORL_KILL_AT=STAGE:STEP`` and
  ``BOTORL_KILL_IN_CHECKPOINT=NAME:PHASE`` make the run kill itself with SIGKILL there; one
  run is killed twice (inside the writer of a BOTO checkpoint, then at the random fine-tuning
  step) and resumed after each kill; slow: killed in every stage in turn (four kills), per
  family. (The own-task CLI test in tests/test_own_task.py kills from outside, at no chosen
  step, as soon as a fine-tuning checkpoint appears.)

Default: every stage on pointmaze, the checkpoint-writer and corruption cases, a control (the
same resume without the env state differs), the twice-killed subprocess run (~1.5 min on 2
loaded cores). ``-m slow`` adds every stage of door, antmaze and kitchen, the four-kill runs
per family, a population of two, and Cal-QL / IQL / RLPD fine-tuning.

Equal means: eval.csv byte for byte (success, return, Q as written, 6 digits); summary.json
except the wall-clock fields (stage_seconds, total_seconds) and run_dir; every metrics/*.jsonl
row (full float precision: losses and Q exactly) except its timing fields (steps_per_s,
env_steps_per_s, seconds); q_probe.csv; D_warmup; and the final agent file byte for byte
(bit-identical parameters, optimiser states and JAX keys). No tolerance: on one machine XLA's
CPU programs are deterministic and a resume replays the same programs on the same inputs.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from botorl.cli import main as botorl_main
from botorl.pipeline import faults

REPO = Path(__file__).resolve().parents[1]
KILL_SEED = int(os.environ.get("BOTORL_KILL_SEED", "15"))
# every stage with mid-stage checkpoints: pre-training 40 steps (chunks of 5), warm-up 30
# env steps, BOTO 30 steps (chunks of 5), fine-tuning from 30 to 80; a checkpoint every 10
ARGS = ["--profile", "smoke", "--no-progress", "--no-tensorboard", "--offline.steps", "40", "--boto.boto_steps", "30",
        "--online.steps", "80", "--checkpoint_every", "10", "--eval.interval", "20"]
TIMING = {"steps_per_s", "env_steps_per_s", "seconds"}
VOLATILE = {"stage_seconds", "total_seconds", "run_dir", "population"}  # wall clock; the directory's own path
MINARI = {"antmaze": "antmaze-large-diverse-v2", "kitchen": "kitchen-partial-v0"}
FAMILIES = {"pointmaze": "pointmaze-umaze", "door": "door-binary-local", **MINARI}


def kill_points(task: str) -> dict[str, int]:
    """A seeded random step in each stage, after its first mid-stage checkpoint where it has one
    (so the resume continues inside the stage; a kill before it restarts the stage, also exact)."""
    rng = random.Random(f"{KILL_SEED}/{task}")
    pts = {"pretrain": rng.randint(11, 39), "warmup": rng.randint(1, 29), "boto": rng.randint(11, 29),
           "finetune": rng.randint(41, 79)}
    print(f"kill points for {task} (BOTORL_KILL_SEED={KILL_SEED}): {pts}")
    return pts


# the checkpoint writer: killed after the agent file (the rest unwritten), and after the
# folder's rename but before latest.json points at it
CKPT_KILLS = [("finetune-step000000050", "files"), ("boto-step000000020", "renamed")]
CORRUPT_AT = ("finetune", 65)  # finetune-step...50 and ...60 exist; the newest is damaged


def _extra_args(task: str, tmp: Path) -> list[str]:
    if task in MINARI.values():
        from test_pipeline_tasks import _data_for  # the small Minari files of the paper-task smoke test

        return _data_for(task, tmp)
    return []


class Reference:
    """One uninterrupted run of ``task`` and the copies of its directory at the kill points."""

    def __init__(self, task: str, root: Path, method_args: tuple[str, ...] = ()):
        self.task, self.root = task, root
        self.points = kill_points(task)
        self.extra = [*_extra_args(task, root), *method_args]
        self.out = root / "reference"
        self.snaps: dict[str, Path] = {}
        want = {**{f"step:{s}": (s, n) for s, n in self.points.items()}, "corrupt": CORRUPT_AT}

        def hook(kind, where, at):
            if kind == "step":
                for key, (stage, n) in want.items():
                    if key not in self.snaps and where == stage and at >= n:
                        self.snaps[key] = self._copy(f"{key.replace(':', '-')}-at{at}")
            elif (where, at) in CKPT_KILLS:
                self.snaps[f"ckpt:{where}:{at}"] = self._copy(f"ckpt-{where}-{at}")

        faults.set_hook(hook)
        try:
            assert botorl_main(["run", "--task", task, *ARGS, *self.extra, "--out", str(self.out)]) == 0
        finally:
            faults.set_hook(None)

    def _copy(self, name: str) -> Path:
        d = self.root / "snap" / name
        shutil.copytree(self.out, d)
        (d / ".lock").unlink(missing_ok=True)  # the killed process's lock (its PID is this test's)
        return d

    def resume_copy(self, key: str, tmp: Path) -> Path:
        """A fresh copy of the snapshot (a test may damage it)."""
        d = tmp / "run"
        shutil.copytree(self.snaps[key], d)
        return d


_refs: dict[str, Reference] = {}


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    def get(task: str) -> Reference:
        if task not in _refs:
            _refs[task] = Reference(task, tmp_path_factory.mktemp(task))
        return _refs[task]

    yield get
    _refs.clear()


def _jsonl(path: Path) -> list[dict]:
    return [{k: v for k, v in json.loads(x).items() if k not in TIMING} for x in path.read_text().splitlines() if x]


def assert_same_run(ref: Path, got: Path, what: str) -> None:
    """``got`` (killed and resumed) ended exactly as ``ref`` (uninterrupted)."""
    assert (got / "eval.csv").read_text() == (ref / "eval.csv").read_text(), what
    s_ref, s_got = (json.loads((d / "summary.json").read_text()) for d in (ref, got))
    assert s_got["status"] == "finished", what
    assert {k: v for k, v in s_got.items() if k not in VOLATILE} == {k: v for k, v in s_ref.items() if k not in VOLATILE}, what
    names = sorted(p.name for p in (ref / "metrics").glob("*.jsonl"))
    assert names == sorted(p.name for p in (got / "metrics").glob("*.jsonl")), what
    for name in names:
        assert _jsonl(got / "metrics" / name) == _jsonl(ref / "metrics" / name), f"{what}: metrics/{name}"
    if (ref / "metrics" / "q_probe.csv").exists():  # RLPD has no offline stage to probe
        assert (got / "metrics" / "q_probe.csv").read_text() == (ref / "metrics" / "q_probe.csv").read_text(), what
    warm = Path("checkpoints") / "warmup-final" / "warmup.npz"
    if (ref / warm).exists():  # a population keeps D_warmup in its own checkpoints
        with np.load(ref / warm) as a, np.load(got / warm) as b:
            assert all(np.array_equal(a[k], b[k]) for k in a.files), f"{what}: D_warmup"
    for path in sorted((ref / "metrics").glob("*.csv")):  # each step logged once, in order
        steps = [row.split(",")[0] for row in path.read_text().splitlines()]
        assert [row.split(",")[0] for row in (got / "metrics" / path.name).read_text().splitlines()] == steps, \
            f"{what}: metrics/{path.name}"
    final = Path("checkpoints") / "finetune-final" / "agent.ckpt"
    assert (got / final).read_bytes() == (ref / final).read_bytes(), f"{what}: the final agent differs"


def _resume(d: Path, capsys) -> str:
    capsys.readouterr()
    assert botorl_main(["resume", str(d), "--no-progress"]) == 0
    return capsys.readouterr().err


# ----------------------------------------------------------------------------- in-process kills
# each stage on pointmaze; the other families are slow (each family's reference costs ~25 s,
# mostly compilation, on a 2-core CPU); the env state itself is checked exactly per family in
# tests/test_envs_state.py
FAST = [("pointmaze", s) for s in ("pretrain", "warmup", "boto", "finetune")]
SLOW = [(f, s) for f in ("door", "antmaze", "kitchen") for s in ("pretrain", "warmup", "boto", "finetune")
        if (f, s) not in FAST]


@pytest.mark.parametrize("family, stage", FAST + [pytest.param(*p, marks=pytest.mark.slow) for p in SLOW],
                         ids=lambda x: x)
def test_kill_in_stage_resumes_exactly(reference, family, stage, tmp_path, capsys):
    ref = reference(FAMILIES[family])
    snap = ref.snaps[f"step:{stage}"]
    d = ref.resume_copy(f"step:{stage}", tmp_path)
    err = _resume(d, capsys)
    if stage != "warmup":  # the warm-up has no mid-stage checkpoint: it starts again
        assert f"from {stage} step" in err, err[-2000:]
    assert_same_run(ref.out, d, f"{ref.task}: killed at {snap.name}")


def test_control_without_env_state_the_run_differs(reference, tmp_path, capsys):
    """The comparison can fail: the same fine-tuning snapshot resumed without its env state (as
    a checkpoint of an older botorl) starts new episodes and ends elsewhere."""
    ref = reference(FAMILIES["pointmaze"])
    d = ref.resume_copy("step:finetune", tmp_path)
    latest = json.loads((d / "checkpoints" / "latest.json").read_text())["name"]
    man = d / "checkpoints" / latest / "MANIFEST.json"
    m = json.loads(man.read_text())
    for f in ("envs.json", "online.npz"):
        (d / "checkpoints" / latest / f).unlink()
        del m["files"][f]
    man.write_text(json.dumps(m))
    err = _resume(d, capsys)
    assert "has no env state" in err
    with pytest.raises(AssertionError):
        assert_same_run(ref.out, d, "control")


@pytest.mark.slow
@pytest.mark.parametrize("method", ["calql", "iql", "rlpd"])
def test_other_methods_resume_exactly_in_finetuning(method, tmp_path, capsys):
    """Fine-tuning's other paths: Cal-QL continued online (Monte-Carlo returns of the running
    episode's rows, updates that wait for the first finished episode, offline mixing), IQL
    (its own update), RLPD (from scratch, random first steps)."""
    ref = Reference(FAMILIES["pointmaze"], tmp_path / "ref", ("--method", method))
    for stage in ("boto", "finetune") if method == "boto" else ("finetune",):
        d = ref.resume_copy(f"step:{stage}", tmp_path / stage)
        err = _resume(d, capsys)
        assert f"from {stage} step" in err, err[-2000:]
        assert_same_run(ref.out, d, f"{method}: killed at {ref.snaps[f'step:{stage}'].name}")


@pytest.mark.parametrize("name, phase", CKPT_KILLS)
def test_kill_inside_checkpoint_writer(reference, name, phase, tmp_path, capsys):
    ref = reference(FAMILIES["pointmaze"])
    d = ref.resume_copy(f"ckpt:{name}:{phase}", tmp_path)
    if phase == "files":  # a half-written temporary folder, latest.json on the checkpoint before
        assert any(p.name.startswith(f".tmp-{name}") for p in (d / "checkpoints").iterdir())
    else:  # complete and in place, but latest.json was not yet pointed at it
        assert (d / "checkpoints" / name / "MANIFEST.json").exists()
    previous = json.loads((d / "checkpoints" / "latest.json").read_text())["name"]
    assert previous != name
    err = _resume(d, capsys)
    assert f"(checkpoint {previous})" in err
    assert not [p.name for p in (d / "checkpoints").iterdir() if p.name.startswith(".tmp-")]
    assert_same_run(ref.out, d, f"killed inside the writer of {name} ({phase})")


def test_corrupted_newest_checkpoint_falls_back(reference, tmp_path, capsys):
    ref = reference(FAMILIES["pointmaze"])
    d = ref.resume_copy("corrupt", tmp_path)
    newest = json.loads((d / "checkpoints" / "latest.json").read_text())["name"]
    assert newest == "finetune-step000000060"
    p = d / "checkpoints" / newest / "buffer.npz"
    b = bytearray(p.read_bytes())
    b[len(b) // 2] ^= 0xFF
    p.write_bytes(bytes(b))
    err = _resume(d, capsys)
    assert newest in err and "sha256" in err and "Falling back to the previous checkpoint, finetune-step000000050" in err
    assert "from finetune step 50" in err
    assert_same_run(ref.out, d, "newest checkpoint corrupted")


# ----------------------------------------------------------------------------- real SIGKILL
def _env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("BOTORL_KILL")}
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.update(extra)
    return env


def _cli(args: list[str], **kill) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "botorl.cli", *args], env=_env(**kill), capture_output=True,
                          text=True, timeout=600)


def _chain(points: dict[str, int], every_stage: bool) -> list[tuple[dict, str]]:
    """(the kill's environment variable, the stage of the newest checkpoint it leaves) per kill."""
    kills = [({"BOTORL_KILL_IN_CHECKPOINT": "boto-step000000020:files"}, "boto"),
             ({"BOTORL_KILL_AT": f"finetune:{points['finetune']}"}, "finetune")]
    if every_stage:
        kills = [({"BOTORL_KILL_AT": f"pretrain:{points['pretrain']}"}, "pretrain"),
                 ({"BOTORL_KILL_AT": f"warmup:{points['warmup']}"}, "pretrain")] + kills  # warm-up: pretrain-final
    return kills


@pytest.mark.timeout(900)
# all slow: test_kill_in_stage_resumes_exactly kills a run in each stage in the default suite
@pytest.mark.parametrize("family, every_stage", [pytest.param("pointmaze", False, marks=pytest.mark.slow)] + [
    pytest.param(f, True, marks=pytest.mark.slow) for f in ("pointmaze", "door", "antmaze", "kitchen")],
    ids=lambda x: {True: "every-stage", False: "twice"}.get(x, x) if isinstance(x, bool) else x)
def test_sigkill_then_resume(reference, family, every_stage, tmp_path):
    """A `botorl run` killed with SIGKILL -- inside the writer of a BOTO checkpoint, then at a random
    step of fine-tuning (slow: first also at a random step of pre-training and of the warm-up) --
    and resumed after each kill ends exactly as the uninterrupted run."""
    ref = reference(FAMILIES[family])
    pts = ref.points
    out = tmp_path / "killed"
    kills = _chain(pts, every_stage)
    for i, (kill, stage) in enumerate(kills):
        args = ["run", "--task", ref.task, *ARGS, *ref.extra, "--out", str(out)] if i == 0 else \
            ["resume", str(out), "--no-progress"]
        res = _cli(args, **kill)
        assert res.returncode == -signal.SIGKILL, f"{kill}: rc {res.returncode}\n{res.stderr[-3000:]}"
        assert json.loads((out / "summary.json").read_text())["status"] == "running"
        latest = json.loads((out / "checkpoints" / "latest.json").read_text())
        assert latest["stage"] == stage, (kill, latest)  # the kill landed in that stage
        if "BOTORL_KILL_IN_CHECKPOINT" in kill:  # the dead writer's half-written folder
            assert any(p.name.startswith(".tmp-boto-step000000020-") for p in (out / "checkpoints").iterdir())
    res = _cli(["resume", str(out), "--no-progress"])
    assert res.returncode == 0, res.stderr[-3000:]
    assert f"from finetune step {(pts['finetune'] // 10) * 10}" in res.stderr
    assert not [p.name for p in (out / "checkpoints").iterdir() if p.name.startswith(".tmp-")]  # the dead writer's
    assert_same_run(ref.out, out, f"{ref.task}: SIGKILL {[k for k, _ in kills]}")


# ----------------------------------------------------------------------------- populations
@pytest.mark.slow
@pytest.mark.timeout(900)  # an uninterrupted population and two killed ones, resumed
def test_population_resumes_exactly(tmp_path, capsys):
    """A population of two (each member its own env) killed in BOTO and in fine-tuning: every
    member, and the population's own checkpoint, end as in the uninterrupted population."""
    out = tmp_path / "pop"
    at = {"boto": 17, "finetune": 53}
    snaps: dict[str, Path] = {}

    def hook(kind, where, step):
        if kind == "step" and where in at and where not in snaps and step >= at[where]:
            snaps[where] = tmp_path / f"snap-{where}"
            shutil.copytree(out, snaps[where])
            (snaps[where] / ".lock").unlink(missing_ok=True)

    faults.set_hook(hook)
    try:
        assert botorl_main(["run", "--task", FAMILIES["pointmaze"], *ARGS, "--seeds", "0,1", "--out", str(out)]) == 0
    finally:
        faults.set_hook(None)
    for stage, d in snaps.items():
        err = _resume(d, capsys)
        assert f"from {stage} step" in err, err[-2000:]
        for m in [m["name"] for m in json.loads((out / "population.json").read_text())["members"]]:
            assert_same_run(out / m, d / m, f"population member {m} killed in {stage}")
        pop = [json.loads((x / "population.json").read_text()) for x in (out, d)]
        for p in pop:
            p["config"].pop("out")  # the directory's own path
        assert [{k: v for k, v in p.items() if k not in VOLATILE} for p in pop][0] == \
            [{k: v for k, v in p.items() if k not in VOLATILE} for p in pop][1]
        final = Path("checkpoints") / "finetune-final" / "agent.ckpt"
        assert (d / final).read_bytes() == (out / final).read_bytes()
        for i in (0, 1):
            w = Path("checkpoints") / "warmup-final" / f"warmup-m{i}.npz"
            with np.load(out / w) as a, np.load(d / w) as b:
                assert all(np.array_equal(a[k], b[k]) for k in a.files)


# ----------------------------------------------------------------------------- W&B cannot hang a run
def test_wandb_that_hangs_is_turned_off(tmp_path, monkeypatch, capsys):
    """A W&B whose init or finish never returns costs $BOTORL_WANDB_TIMEOUT seconds and a warning,
    not the run (W&B is optional; the fake module stands in for it, which is not installed)."""
    import threading
    import time
    import types
    from dataclasses import replace

    from botorl.configs.presets import make_preset
    from botorl.pipeline import tracking
    from botorl.pipeline.rundir import RunDir

    never = threading.Event()
    fake = types.ModuleType("wandb")
    fake.init = lambda **kw: never.wait()
    monkeypatch.setitem(sys.modules, "wandb", fake)
    monkeypatch.setenv("BOTORL_WANDB_TIMEOUT", "0.3")
    cfg = replace(make_preset(FAMILIES["pointmaze"], "smoke"), wandb=True)
    t0 = time.perf_counter()
    assert tracking.start([cfg], [RunDir(tmp_path / "run")]) == [None]
    assert time.perf_counter() - t0 < 5
    assert "W&B did not start within 0.3 s" in capsys.readouterr().err

    class Run:
        def define_metric(self, *a, **kw):
            pass

        def finish(self, exit_code=0):
            never.wait()

    fake.init = lambda **kw: Run()
    (wb,) = tracking.start([cfg], [RunDir(tmp_path / "run")])
    assert isinstance(wb, Run)
    t0 = time.perf_counter()
    tracking.finish([wb])
    assert time.perf_counter() - t0 < 5
    assert "W&B did not finish within 0.3 s" in capsys.readouterr().err

    def refuse(**kw):
        raise ConnectionError("no network")

    fake.init = refuse
    assert tracking.start([cfg], [RunDir(tmp_path / "run")]) == [None]
    assert "ConnectionError: no network" in capsys.readouterr().err
    never.set()


def test_population_file_names_the_member_directories(tmp_path):
    """BOTO without --alphas: members take the preset's alpha but their directories are seed<k>;
    population.json must name those (`botorl resume POPDIR` reads them)."""
    from botorl.pipeline.cli import build_config
    from botorl.configs.members import member_config
    from botorl.pipeline.summary import write_population_file

    cfg = build_config(["--task", FAMILIES["pointmaze"], "--profile", "smoke"])
    assert cfg.alpha is not None
    members = [member_config(cfg, s, None, tmp_path / f"seed{s}") for s in (0, 1)]
    write_population_file(tmp_path, cfg, members, "running", ["running"] * 2, {})
    pop = json.loads((tmp_path / "population.json").read_text())
    assert [(m["name"], m["alpha"]) for m in pop["members"]] == [("seed0", cfg.alpha), ("seed1", cfg.alpha)]


def test_generated_data_with_wide_actions_reads_back_from_its_cache(monkeypatch, tmp_path):
    """door-binary-local's data hold the DAPG demos' actions (up to |a| = 1.37, accepted by the
    task's action_tolerance): read back from the cache (a second run, any resume) they must not be
    rejected with the default tolerance. A tiny stand-in generator with actions up to 1.3."""
    from botorl.data import generate as G
    from botorl.data.dataset import Dataset

    def fake(steps, seed, progress=True):
        rng = np.random.default_rng(seed)
        obs = rng.normal(size=(steps + 1, 3)).astype(np.float32)
        ends = np.zeros(steps, bool)
        ends[-1] = True
        return Dataset(obs[:-1], rng.uniform(-1.3, 1.3, (steps, 2)).astype(np.float32), np.zeros(steps, np.float32),
                       obs[1:], np.zeros(steps, bool), ends, metadata={"source": "test"})

    monkeypatch.setenv("BOTORL_DATA_DIR", str(tmp_path))
    monkeypatch.setattr(G, "get_generator", lambda task: fake)
    first = G.ensure_dataset("door-binary-local", 40, 0, progress=False)
    again = G.ensure_dataset("door-binary-local", 40, 0, progress=False)  # from the cache
    assert first.raw_action_max > 1.2 and np.isclose(again.raw_action_max, first.raw_action_max)
    assert np.array_equal(first.actions, again.actions)

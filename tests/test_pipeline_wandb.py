"""W&B (``--wandb``) for populations and sweeps: one W&B run per member, ids unique to the run
directory, one group per task/method/alpha, curves against online env steps, config logged;
a missing wandb fails before any directory exists; ``sweep --set wandb=True`` passes.

Most of it runs against a stand-in ``wandb`` module that records every call (wandb is not a
dependency; CI does not install it). ``test_real_wandb_offline`` runs the real one in offline
mode where it is importable.
"""

from __future__ import annotations

import sys
import types
from pathlib import Path

import pytest

from botorl.cli import main as botorl_main
from botorl.pipeline import tracking
from test_reliability_resume import ARGS

TASK = "pointmaze-umaze"
POP = ["run", "--task", TASK, *ARGS, "--seeds", "0-1", "--wandb"]


class FakeRun:
    def __init__(self, calls: list, **kw):
        self.kw, self.calls = kw, calls
        self.id, self.group, self.job_type = kw["id"], kw["group"], kw["job_type"]

    def define_metric(self, name, **kw):
        self.calls.append(("define_metric", self.id, name, kw))

    def log(self, data):
        self.calls.append(("log", self.id, dict(data)))

    def finish(self, exit_code=0):
        self.calls.append(("finish", self.id, exit_code))


@pytest.fixture
def fake_wandb(monkeypatch):
    calls: list = []
    mod = types.ModuleType("wandb")
    mod.__version__ = "0.19.10"

    def init(**kw):
        calls.append(("init", kw))
        return FakeRun(calls, **kw)

    mod.init = init
    monkeypatch.setitem(sys.modules, "wandb", mod)
    return calls


def test_population_logs_one_wandb_run_per_member(fake_wandb, tmp_path):
    out = tmp_path / "pop"
    assert botorl_main([*POP, "--out", str(out)]) == 0
    inits = [kw for c, kw in (c[:2] for c in fake_wandb) if c == "init"]
    assert len(inits) == 2
    assert len({kw["id"] for kw in inits}) == 2  # one run per member
    assert {kw["id"] for kw in inits} == {tracking.run_id(out / m) for m in ("seed0", "seed1")}
    assert {kw["group"] for kw in inits} == {f"{TASK}/boto/alpha-1.00"}  # one group
    assert {kw["job_type"] for kw in inits} == {"pretrain+warmup+boto+finetune"}
    assert sorted(kw["config"]["seed"] for kw in inits) == [0, 1]  # each member's own config
    assert all(kw["reinit"] == "create_new" and kw["resume"] == "allow" for kw in inits)
    for kw in inits:
        defined = {c[2]: c[3] for c in fake_wandb if c[0] == "define_metric" and c[1] == kw["id"]}
        for key in ("eval/*", "finetune/*", "warmup/*"):
            assert defined[key] == {"step_metric": "env_step"}, key
        assert defined["pretrain/*"] == {"step_metric": "pretrain/step"}
        logs = [c[2] for c in fake_wandb if c[0] == "log" and c[1] == kw["id"]]
        evals = [d for d in logs if "eval/success" in d]
        assert evals and all(d["env_step"] == d["eval/env_step"] for d in evals)
        assert max(d["env_step"] for d in evals) == 80  # the online axis, to online.steps
        assert any("finetune/critic_loss" in d and "env_step" in d for d in logs)
        assert ("finish", kw["id"], 0) in fake_wandb


def test_run_ids_are_unique_to_the_directory(tmp_path):
    """Not the last path component: /a/boto/seed0 and /b/wsrl/seed0 are two W&B runs; the same
    directory (a resume) the same one."""
    a, b = tmp_path / "a" / "boto" / "seed0", tmp_path / "b" / "wsrl" / "seed0"
    assert tracking.run_id(a) != tracking.run_id(b)
    assert tracking.run_id(a) == tracking.run_id(tmp_path / "a" / "x" / ".." / "boto" / "seed0")


@pytest.mark.parametrize("argv", [["run", "--task", TASK, "--profile", "smoke", "--wandb"], POP],
                         ids=["single", "population"])
def test_missing_wandb_fails_before_the_run_directory_exists(monkeypatch, tmp_path, capsys, argv):
    monkeypatch.setitem(sys.modules, "wandb", None)  # `import wandb` raises ImportError
    out = tmp_path / "run"
    assert botorl_main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert 'pip install "botorl[wandb]"' in err
    assert not out.exists()


def test_old_wandb_is_refused(fake_wandb, monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(sys.modules["wandb"], "__version__", "0.16.6")
    out = tmp_path / "run"
    assert botorl_main(["run", "--task", TASK, "--profile", "smoke", "--wandb", "--out", str(out)]) == 2
    assert "wandb >= 0.19.10" in capsys.readouterr().err and not out.exists()


def test_sweep_set_passes_boolean_flags(monkeypatch, tmp_path, capsys):
    """`--set wandb=True` becomes `--wandb` (tyro's bools are flags), `x=False` `--no-x`
    (nested: `--a.no-b`); a `bool | None` field keeps its value. With wandb missing the sweep
    stops before its first trial."""
    from botorl.configs.build import build_config
    from botorl.experiments.grid import build_grid

    grid = build_grid(tasks=TASK, methods="boto", seeds="0", profile="smoke",
                      overrides=["wandb=True", "tensorboard=false", "offline.cql.cql_lagrange=True",
                                 "network.layer_norm=False", "offline.sample_on_device=True"])
    cfg = grid.config(grid.trials()[0])  # each the opposite of the smoke preset's
    assert cfg.wandb and not cfg.tensorboard and cfg.offline.cql.cql_lagrange and not cfg.network.layer_norm
    assert cfg.offline.sample_on_device is True
    assert cfg == build_config(["--task", TASK, "--method", "boto", "--seed", "0", "--profile", "smoke", "--wandb",
                                "--no-tensorboard", "--offline.cql.cql-lagrange", "--network.no-layer-norm",
                                "--offline.sample_on_device", "True"])
    monkeypatch.setitem(sys.modules, "wandb", None)
    out = tmp_path / "sweep"
    assert botorl_main(["sweep", "--tasks", TASK, "--methods", "boto", "--seeds", "0", "--profile", "smoke",
                        "--set", "wandb=True", "--out", str(out), "--no-progress"]) == 2
    assert 'pip install "botorl[wandb]"' in capsys.readouterr().err
    assert not list(out.glob("**/config.json"))


def test_real_wandb_offline(tmp_path, monkeypatch):
    """`WANDB_MODE=offline botorl run --seeds 0-1 --wandb`: two W&B runs, distinct ids, one group,
    each written under its member's directory."""
    wandb = pytest.importorskip("wandb")
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    runs = []
    real_init = wandb.init

    def spy(**kw):
        r = real_init(**kw)
        runs.append(r)
        return r

    monkeypatch.setattr(wandb, "init", spy)
    out = tmp_path / "pop"
    assert botorl_main([*POP, "--out", str(out)]) == 0
    assert len(runs) == 2
    assert len({r.id for r in runs}) == 2 and len({r.group for r in runs}) == 1
    for m in ("seed0", "seed1"):
        (d,) = (out / m / "wandb").glob(f"offline-run-*-{tracking.run_id(out / m)}")
        assert any(p.suffix == ".wandb" for p in d.iterdir())


def test_wandb_dir_is_honoured(fake_wandb, tmp_path, monkeypatch):
    """W&B's files go where $WANDB_DIR says when it is set (W&B's convention), else into the run
    directory (issue 42)."""
    from botorl.configs.schema import RunConfig
    from botorl.pipeline.rundir import RunDir

    cfg = RunConfig(wandb=True)
    monkeypatch.delenv("WANDB_DIR", raising=False)
    tracking.start([cfg], [RunDir(tmp_path / "a")])
    monkeypatch.setenv("WANDB_DIR", str(tmp_path / "scratch"))
    tracking.start([cfg], [RunDir(tmp_path / "b")])
    dirs = [c[1]["dir"] for c in fake_wandb if c[0] == "init"]
    assert dirs == [str(tmp_path / "a"), str(tmp_path / "scratch")]

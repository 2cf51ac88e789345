"""A whole run (smoke profile) through the CLI: the run-directory contract, every method,
evaluation, and a divergence that stops the run with the last good checkpoint kept.

One module-scoped BOTO run is shared by several tests; runs are in-process so that jitted
functions compile once.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from botorl.cli import main as botorl_main

TASK = "pointmaze-umaze"
SUMMARY_KEYS = {"task", "method", "seed", "alpha", "pretrain", "success_initial", "success_10k", "success_final",
                "stage_seconds", "status"}


def _run(out: Path, *args: str) -> int:
    return botorl_main(["run", "--task", TASK, "--profile", "smoke", "--no-progress", "--no-tensorboard",
                        "--out", str(out), *args])


def _csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


EVAL_CALLS: list[int] = []


@pytest.fixture(scope="module")
def boto_run(tmp_path_factory):
    from botorl.pipeline import evaluation

    out = tmp_path_factory.mktemp("pipeline") / "boto"
    run_episodes = evaluation.run_episodes

    def counted(*args, **kwargs):
        EVAL_CALLS.append(1)
        return run_episodes(*args, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(evaluation, "run_episodes", counted)
        assert _run(out, "--seed", "3", "--alpha", "-0.5") == 0
    return out


def test_run_directory_contract(boto_run):
    d = boto_run
    cfg = json.loads((d / "config.json").read_text())
    assert (cfg["task"], cfg["method"], cfg["seed"], cfg["alpha"], cfg["pretrain"], cfg["profile"]) == (
        TASK, "boto", 3, -0.5, "calql", "smoke")
    assert "alpha" not in cfg["boto"] and "seed" not in cfg["boto"]  # stored once, at the top level

    rows = _csv(d / "eval.csv")
    assert list(rows[0].keys()) == ["stage", "env_step", "success", "return", "q_data", "q_uniform"]
    # smoke: 40 online steps of which the first 30 are the warm-up (WSRL's accounting): the
    # pre-trained policy is evaluated at 0 and 20 during the warm-up, the BOTO-trained one when
    # fine-tuning starts (30), then at 40 (the end)
    assert [(r["stage"], int(r["env_step"])) for r in rows] == [
        ("warmup", 0), ("warmup", 20), ("finetune", 30), ("finetune", 40)]
    # the frozen policy's evaluation at 20 is the one at 0, logged again, not run again
    assert len(EVAL_CALLS) == 3
    assert {k: v for k, v in rows[1].items() if k != "env_step"} == {k: v for k, v in rows[0].items() if k != "env_step"}
    for r in rows:
        assert 0.0 <= float(r["success"]) <= 1.0
        assert math.isfinite(float(r["q_data"])) and math.isfinite(float(r["q_uniform"]))
    ft = _csv(d / "metrics" / "finetune.csv")
    assert ft and all(30 < int(float(r["step"])) <= 40 for r in ft)

    for stage in ("pretrain", "warmup", "boto", "finetune"):
        assert (d / "metrics" / f"{stage}.csv").stat().st_size > 0
        lines = (d / "metrics" / f"{stage}.jsonl").read_text().splitlines()
        assert lines and all("step" in json.loads(x) for x in lines)
        assert (d / "checkpoints" / f"{stage}-final" / "agent.ckpt").is_file()
    assert (d / "checkpoints" / "warmup-final" / "warmup.npz").is_file()
    latest = json.loads((d / "checkpoints" / "latest.json").read_text())
    assert latest["name"] == "finetune-final" and latest["stage_done"]
    # intermediate checkpoints are pruned once the stage's final one exists
    assert not [p for p in (d / "checkpoints").iterdir() if "-step" in p.name or p.name.startswith(".")]

    png = (d / "curve.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"

    s = json.loads((d / "summary.json").read_text())
    assert SUMMARY_KEYS <= set(s)
    assert s["status"] == "finished" and s["task"] == TASK and s["method"] == "boto" and s["alpha"] == -0.5
    assert set(s["stage_seconds"]) == {"pretrain", "warmup", "boto", "finetune"}
    assert s["success_initial"] == float(rows[0]["success"]) and s["success_final"] == float(rows[-1]["success"])
    assert s["success_10k"] is None  # 40 online steps never reach 10k

    # the warm-up dataset has the run's length and transformed rewards (pointmaze: 10 r - 5)
    with np.load(d / "checkpoints" / "warmup-final" / "warmup.npz") as z:
        assert len(z["rewards"]) == cfg["warmup"]["steps"]
        assert set(np.unique(z["rewards"])) <= {-5.0, 5.0}


def test_q_probe_logged_per_stage(boto_run):
    rows = _csv(boto_run / "metrics" / "q_probe.csv")
    assert [r["stage"] for r in rows] == ["pretrain", "boto"]
    # BOTO changed the critic: Q on the probe moved
    assert rows[0]["q_uniform"] != rows[1]["q_uniform"]


def test_eval_command(boto_run, capsys):
    assert botorl_main(["eval", str(boto_run), "--episodes", "2"]) == 0
    out = capsys.readouterr().out
    assert "success" in out and "q_uniform" in out
    res = json.loads((boto_run / "eval-finetune-final.json").read_text())
    assert res["episodes"] == 2 and 0.0 <= res["success"] <= 1.0 and res["stage"] == "finetune"
    # a stage's final checkpoint is at the stage's last step (the smoke profile's 40 online steps)
    assert res["step"] == 40 and "None" not in out


def test_resume_of_finished_run_is_a_no_op(boto_run, capsys):
    before = (boto_run / "eval.csv").read_text()
    assert botorl_main(["resume", str(boto_run)]) == 0
    assert "finished already" in capsys.readouterr().err
    assert (boto_run / "eval.csv").read_text() == before


@pytest.mark.parametrize(
    "method, stages, pretrain, eval_steps",
    [
        # one online axis: wsrl's 30 warm-up steps are online steps, fine-tuning starts at 30
        ("wsrl", ["pretrain", "warmup", "finetune"], "calql", [0, 20, 30, 40]),
        ("calql", ["pretrain", "finetune"], "calql", [0, 20, 40]),
        ("iql", ["pretrain", "finetune"], "iql", [0, 20, 40]),
        ("rlpd", ["finetune"], None, [0, 20, 40]),
    ],
)
def test_methods_run_their_stages(tmp_path, method, stages, pretrain, eval_steps):
    out = tmp_path / method
    assert _run(out, "--method", method) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["status"] == "finished" and s["method"] == method and s["pretrain"] == pretrain and s["alpha"] is None
    assert list(s["stage_seconds"]) == stages
    assert [int(r["env_step"]) for r in _csv(out / "eval.csv")] == eval_steps
    assert not (out / "checkpoints" / "boto-final").exists()


def test_dense_window_and_online_reseed_over_one_pretraining(boto_run, tmp_path):
    # WSRL from the BOTO run's pre-training: the dense window evaluates every 5 steps from the
    # warm-up's end (30) on; --online-reseed 1 changes the online phase only, so the step-0
    # evaluation (the shared pre-trained policy) agrees and the fine-tuning numbers do not.
    def wsrl(name, *flags):
        out = tmp_path / name
        assert _run(out, "--method", "wsrl", "--seed", "3", "--pretrained", str(boto_run),
                    "--eval.dense-interval", "5", *flags) == 0
        return _csv(out / "eval.csv"), _csv(out / "metrics" / "finetune.csv")

    (evals, ft), (evals_r, ft_r) = wsrl("same"), wsrl("reseeded", "--online-reseed", "1")
    assert [int(r["env_step"]) for r in evals] == [0, 20, 30, 35, 40] == [int(r["env_step"]) for r in evals_r]
    assert evals[0]["success"] == evals_r[0]["success"] and evals[0]["q_data"] == evals_r[0]["q_data"]
    assert [r["critic_loss"] for r in ft] != [r["critic_loss"] for r in ft_r]


def test_quick_profile_evaluates_densely_in_the_dip_window():
    from botorl.configs.presets import make_preset
    from botorl.configs.resolve import resolve

    for method in ("boto", "wsrl", "calql", "rlpd"):
        cfg = resolve(make_preset("pointmaze-medium", "quick", method))
        start = cfg.warmup.steps
        points = [t for t in range(start, cfg.online.steps + 1) if cfg.eval.due(t, cfg.online.steps, start)]
        # every method is evaluated at the same points from the warm-up's end to 10k, >= 10 of them
        assert [t for t in points if t <= 10_000] == list(range(5_000, 10_001, 500)), method
        assert points[-1] == cfg.online.steps


def test_pretrain_can_sample_on_the_device(tmp_path):
    # --offline.sample_on_device: the batches are drawn inside the jitted call from a key
    # that follows from (seed, step): two runs agree, and differ from numpy sampling.
    def pretrain_losses(name, *flags):
        out = tmp_path / name
        assert _run(out, "--method", "iql", "--online.steps", "20", *flags) == 0
        return [(r["step"], r["critic_loss"], r["q_data"]) for r in _csv(out / "metrics" / "pretrain.csv")]

    a = pretrain_losses("device_a", "--offline.sample_on_device", "True")
    b = pretrain_losses("device_b", "--offline.sample_on_device", "True")
    host = pretrain_losses("host", "--offline.sample_on_device", "False")
    assert a == b and len(a) >= 2
    assert [r[0] for r in a] == [r[0] for r in host] and a != host


def test_divergence_stops_with_last_good_checkpoint(tmp_path, monkeypatch, capsys):
    """A NaN loss in fine-tuning: exit 2, status failed, the checkpoint before it kept."""
    from botorl.agents import population

    # every fine-tuning update of SAC goes through the population's batched update, fused with
    # the next step's action (a run is a population of one)
    real_update = population.update_then_sample
    calls = {"n": 0}

    def poisoned(agents, batches, observations, **kw):
        agents, metrics, actions, rng = real_update(agents, batches, observations, **kw)
        calls["n"] += 1
        if calls["n"] >= 25:
            metrics = dict(metrics, critic_loss=np.full((1,), np.nan, np.float32))
        return agents, metrics, actions, rng

    monkeypatch.setattr(population, "update_then_sample", poisoned)
    out = tmp_path / "nan"
    code = _run(out, "--online.steps", "80")  # fine-tuning from 30 (after the warm-up) to 80
    err = capsys.readouterr().err
    assert code == 2
    assert "diverged" in err and "critic_loss = nan" in err and "finetune" in err
    s = json.loads((out / "summary.json").read_text())
    assert s["status"] == "failed" and "diverged" in s["error"]
    latest = json.loads((out / "checkpoints" / "latest.json").read_text())
    # the mid-stage checkpoint at step 40 was written before the NaN (update 25, step 55); nothing after
    assert latest["name"] == "finetune-step000000040"
    assert not (out / "checkpoints" / "finetune-final").exists()


def test_summary_text_of_a_run_shorter_than_10k(boto_run):
    from botorl.pipeline.summary import format_summary

    text = format_summary(json.loads((boto_run / "summary.json").read_text()))
    assert "env step -" not in text and "no evaluation at 10k: the run ends at env step 40" in text

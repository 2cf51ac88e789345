"""A task without success (issue 42): the headline metric is the return (or, with reference
scores, D4RL's normalised score) in summary.json, curve.png, the printed summary, `botorl eval`
and `botorl report`; Gymnasium's Pendulum-v1 end to end through examples/pendulum.py."""

from __future__ import annotations

import csv
import json
import os
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import load_example
from helpers import subprocess_env as _env

import botorl
from botorl.cli import main as cli_main
from botorl.envs.metric import Metric, check_refs, headline_of_summary, normalised_score, of_config
from botorl.errors import ConfigError
from botorl.experiments.report import make_report
from botorl.pipeline.summary import format_population, format_summary


REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "pendulum.py"


def _example():
    return load_example("pendulum")


# ------------------------------------------------------------------ the metric itself
def test_normalised_score_is_d4rls():
    # D4RL: 100 * (R - random) / (expert - random)
    assert normalised_score(-1238.0, -1238.0, -142.0) == pytest.approx(0.0)
    assert normalised_score(-142.0, -1238.0, -142.0) == pytest.approx(100.0)
    assert normalised_score(-690.0, -1238.0, -142.0) == pytest.approx(50.0)
    m = Metric("score", -1238.0, -142.0)
    assert m.column == "return" and not m.bounded and m.of(1.0, -690.0) == pytest.approx(50.0)
    assert Metric("return").of(1.0, -3.5) == -3.5 and Metric().of(0.25, -3.5) == 0.25


def test_of_config_reads_records_and_old_runs():
    assert of_config({"metric": {"name": "return"}}) == Metric("return")
    assert of_config({"metric": {"name": "score", "ref_min_score": 0, "ref_max_score": 10}}) == Metric("score", 0.0, 10.0)
    assert of_config({"metric": {"name": "score", "ref_min_score": 5, "ref_max_score": 1}}) == Metric("return")
    assert of_config({}) == Metric("success")  # a goal task's run from before the record
    assert of_config({"env": {"success_off": "no key"}}) == Metric("return")  # a success-less one
    assert of_config({"metric": "garbage", "env": []}) == Metric("success")


@pytest.mark.parametrize("lo,hi,message", [(1.0, None, "give both"), (5.0, 1.0, "must be below"),
                                           (float("nan"), 1.0, "finite numbers"), ("a", 1.0, "finite numbers")])
def test_bad_reference_scores(lo, hi, message):
    with pytest.raises(ConfigError, match=message):
        check_refs(lo, hi, "task 't'")
    assert check_refs(None, None, "t") == (None, None)


def test_register_task_refuses_half_reference_scores():
    pendulum = _example()
    data = pendulum.logged_data(episodes=2)
    with pytest.raises(botorl.BotorlError, match="give both ref_min_score and ref_max_score"):
        botorl.register_task("pendulum-bad", pendulum.make_env, data, max_episode_steps=200, ref_min_score=-1000.0)
    spec = botorl.register_task("pendulum-refs", pendulum.make_env, data, max_episode_steps=200,
                                ref_min_score=-1200.0, ref_max_score=-150.0)
    assert (spec.ref_min_score, spec.ref_max_score) == (-1200.0, -150.0)


def test_printed_summary_names_the_metric():
    base = {"task": "t", "method": "boto", "seed": 0, "alpha": 0.0, "pretrain": "calql", "profile": "smoke",
            "status": "finished", "stage_seconds": {"pretrain": 1.0}, "total_seconds": 1.0, "env_step_10k": None,
            "env_step_final": 40, "run_dir": "/r"}
    ret = dict(base, return_initial=-1500.5, return_10k=None, return_final=-1400.25)
    assert headline_of_summary(ret) == "return"
    text = format_summary(ret)
    assert re.search(r"^return +initial", text, re.M) and "-1500.500" in text and "success" not in text
    assert format_population([ret]).splitlines()[0] == "return:"
    goal = dict(base, success_initial=1.0, success_10k=None, success_final=0.5, **{k: v for k, v in ret.items()
                                                                                  if k.startswith("return_")})
    assert headline_of_summary(goal) == "success" and re.search(r"^success +initial", format_summary(goal), re.M)
    assert format_population([goal]).splitlines()[0].startswith("member")  # as before the metric
    score = dict(ret, score_initial=12.5, score_10k=None, score_final=20.0)
    assert re.search(r"^score +initial", format_summary(score), re.M) and "12.500" in format_summary(score)


# ------------------------------------------------------------------ the report, from hand-made runs
def _write(root: Path, task: str, method: str, seed: int, returns: list[tuple[int, float]], metric: dict,
           env: dict | None = None) -> Path:
    d = root / task / method / f"seed{seed}"
    d.mkdir(parents=True)
    meta = {"task": task, "method": method, "seed": seed, "alpha": None, "pretrain": "calql", "profile": "quick"}
    (d / "config.json").write_text(json.dumps(dict(meta, metric=metric, env=env or {})))
    vals = dict(returns)
    summary = dict(meta, return_initial=vals[0], return_10k=vals[10_000], return_final=returns[-1][1],
                   status="finished")
    if metric["name"] == "score":
        m = of_config({"metric": metric})
        summary.update({f"score_{p}": m.of(math.nan, summary[f"return_{p}"]) for p in ("initial", "10k", "final")})
    (d / "summary.json").write_text(json.dumps(summary))
    with open(d / "eval.csv", "w") as f:
        f.write("stage,env_step,success,return,q_data,q_uniform\n")
        for step, r in returns:
            f.write(f"finetune,{step},0,{r},0,0\n")
    return d


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    """Two success-less tasks: 'pend' in return (2 seeds per method), 'pend-score' in the
    normalised score with references -1000 / -200."""
    root = tmp_path_factory.mktemp("runs")
    ret = {"name": "return", "ref_min_score": None, "ref_max_score": None}
    score = {"name": "score", "ref_min_score": -1000.0, "ref_max_score": -200.0}
    # wsrl falls from -200 to -600 (dip -400) and -300 to -500 (dip -200); boto -200 -> -300, -300 -> -300
    for seed, (r0, low, end) in enumerate([(-200.0, -600.0, -150.0), (-300.0, -500.0, -250.0)]):
        _write(root, "pend", "wsrl", seed, [(0, r0), (5_000, low), (10_000, -400.0), (20_000, end)], ret)
    for seed, (r0, low) in enumerate([(-200.0, -300.0), (-300.0, -300.0)]):
        _write(root, "pend", "boto", seed, [(0, r0), (5_000, low), (10_000, -250.0), (20_000, -200.0)], ret)
    # in score: -200 -> 100, -600 -> 50, -1000 -> 0
    _write(root, "pend-score", "wsrl", 0, [(0, -200.0), (5_000, -600.0), (10_000, -1000.0), (20_000, -200.0)], score)
    out = root / "report"
    return make_report([root], out, n_boot=200), out


def test_report_table1_and_dip_in_the_return(report):
    result, out = report
    md = (out / "report.md").read_text()
    assert "## Table 1: the headline metric of each task, mean ± standard error over seeds" in md
    assert "- pend: episode return" in md and "- pend-score: normalised score, 100 * (return - ref_min) / (ref_max - ref_min) with the task's reference " \
        "scores ref_min -1000, ref_max -200" in md
    rows = {(r["task"], r["method"]): r for r in csv.DictReader((out / "table1.csv").open())}
    assert float(rows[("pend", "wsrl")]["initial_mean"]) == pytest.approx(-250.0)
    assert float(rows[("pend", "wsrl")]["final_mean"]) == pytest.approx(-200.0)
    assert float(rows[("pend-score", "wsrl")]["initial_mean"]) == pytest.approx(100.0)
    assert float(rows[("pend-score", "wsrl")]["10k_mean"]) == pytest.approx(0.0)
    # the dip: lowest return in 0..10k minus the return at 0
    assert float(rows[("pend", "wsrl")]["dip_mean"]) == pytest.approx((-400.0 + -200.0) / 2)
    assert float(rows[("pend", "boto+calql")]["dip_mean"]) == pytest.approx((-100.0 + 0.0) / 2)
    assert float(rows[("pend-score", "wsrl")]["dip_mean"]) == pytest.approx(-100.0)  # 100 -> 0
    assert "the lowest headline metric over every evaluation" in md and "| headline metric at 0 |" in md
    assert "-1 = from always" not in md
    dips = list(csv.DictReader((out / "dip_runs.csv").open()))
    assert "headline_metric_0" in dips[0]
    # returns of two tasks are not pooled into one IQM
    assert any("no aggregate over pend, pend-score" in n for n in result.notes)
    # the paired comparison (same pre-training fingerprint: none here, the configs record none)
    assert (out / "figure5.png").exists() and (out / "dip.png").exists()


def test_report_of_one_metric_names_it(tmp_path):
    ret = {"name": "return", "ref_min_score": None, "ref_max_score": None}
    for seed in range(2):
        _write(tmp_path / "runs", "pend", "wsrl", seed, [(0, -200.0), (10_000, -300.0), (20_000, -100.0)], ret,
               env={"success_off": "the env's info has no 'success' key"})
    make_report([tmp_path / "runs"], tmp_path / "report", n_boot=100)
    md = (tmp_path / "report" / "report.md").read_text()
    assert "## Table 1: return, mean ± standard error over seeds" in md
    assert "| return at 0 |" in md and "the lowest return over every evaluation" in md
    assert "success is off on pend" in md and "the report is in the return there" in md


# ------------------------------------------------------------------ Pendulum-v1, end to end
@pytest.fixture(scope="module")
def pendulum(tmp_path_factory):
    """examples/pendulum.py with the smoke profile: BOTO, WSRL, their report, the policy."""
    out = tmp_path_factory.mktemp("pendulum")
    proc = subprocess.run([sys.executable, str(EXAMPLE), "--profile", "smoke", "--out", str(out / "runs")],
                          cwd=out, env=_env(), capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out / "runs", proc.stdout


@pytest.mark.timeout(600)
def test_pendulum_summary_curve_and_table_are_in_return(pendulum):
    runs, stdout = pendulum
    for method in ("boto", "wsrl"):
        s = json.loads((runs / method / "summary.json").read_text())
        assert s["status"] == "finished" and s["task"] == "pendulum"
        assert not any(k.startswith("success_") and k != "success_off" for k in s), s  # absent, not 0
        assert all(isinstance(s[f"return_{p}"], float) for p in ("initial", "final")) and s["return_10k"] is None
        assert s["return_initial"] < 0  # Pendulum's reward is <= 0
        assert json.loads((runs / method / "config.json").read_text())["metric"]["name"] == "return"
        assert (runs / method / "curve.png").stat().st_size > 0
        rows = list(csv.DictReader((runs / method / "eval.csv").open()))
        assert float(rows[-1]["return"]) == pytest.approx(s["return_final"], rel=1e-5)
    assert re.search(r"^return +initial", stdout, re.M) and not re.search(r"^success +initial", stdout, re.M)
    assert "boto: status finished, return" in stdout and "boto's policy in a plain Gymnasium loop: return" in stdout
    md = (runs / "report" / "report.md").read_text()
    assert "## Table 1: return, mean ± standard error over seeds" in md and "| return at 0 |" in md
    assert "| pendulum | boto+calql |" in md


@pytest.mark.timeout(600)
def test_pendulum_eval_prints_the_return(pendulum, capsys):
    runs, _ = pendulum
    example = _example()
    # the task was registered from a script: register it again in this process (docs/own-task.md)
    botorl.register_task("pendulum", example.make_env, example.logged_data(), max_episode_steps=200,
                         reward_scale=0.1)
    capsys.readouterr()
    assert cli_main(["eval", str(runs / "boto"), "--episodes", "2"]) == 0
    printed = capsys.readouterr().out
    assert "return " in printed and "success" not in printed
    result = json.loads(next((runs / "boto").glob("eval-*.json")).read_text())
    assert "success" not in result and result["return"] < 0 and result["episodes"] == 2
    # the policy drives Pendulum-v1 within its torque bounds
    policy = botorl.load_policy(runs / "boto")
    a = policy(np.array([1.0, 0.0, 0.0], np.float32))
    assert a.shape == (1,) and -2.0 <= float(a[0]) <= 2.0


# ------------------------------------------------------------------ --ref-min-score / --ref-max-score
DRIFT = '''
import gymnasium as gym
import numpy as np
from gymnasium import spaces

class Drift(gym.Env):
    """No success; reward -|x| per step, x moved by the action (in [-0.5, 0.5])."""
    observation_space = spaces.Box(-5, 5, (1,), np.float32)
    action_space = spaces.Box(-0.5, 0.5, (1,), np.float32)
    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x = 1.0
        return np.array([self.x], np.float32), {}
    def step(self, a):
        self.x = float(np.clip(self.x + float(a[0]), -5, 5))
        return np.array([self.x], np.float32), -abs(self.x), False, False, {}

def make_env(seed):
    return Drift()
'''


@pytest.fixture(scope="module")
def drift(tmp_path_factory):
    d = tmp_path_factory.mktemp("drift")
    (d / "drift.py").write_text(DRIFT)
    rng = np.random.default_rng(0)
    n, horizon = 400, 20
    obs = rng.uniform(-2, 2, (n, 1)).astype(np.float32)
    act = rng.uniform(-0.5, 0.5, (n, 1)).astype(np.float32)
    nxt = np.clip(obs + act, -5, 5)
    np.savez(d / "logged.npz", observations=obs, actions=act, next_observations=nxt, rewards=-np.abs(nxt[:, 0]),
             terminals=np.zeros(n, bool), timeouts=(np.arange(n) % horizon) == horizon - 1)
    return d


def _drift_cli(drift, monkeypatch, capsys, *args, out=None):
    monkeypatch.chdir(drift)
    monkeypatch.delitem(sys.modules, "drift", raising=False)
    argv = ["run", "--env", "drift:make_env", "--data.path", "logged.npz", "--env-max-steps", "20", *args,
            "--profile", "smoke", "--no-progress", "--no-tensorboard", "--out", str(out or drift / "runs" / "bad")]
    code = cli_main(argv)
    return code, " ".join(capsys.readouterr().err.split())


@pytest.mark.parametrize("args,message", [
    (["--ref-min-score", "-10"], "give both ref_min_score and ref_max_score"),
    (["--ref-min-score", "0", "--ref-max-score", "-10"], "ref_min_score 0 must be below ref_max_score -10"),
    (["--ref-min-score", "low", "--ref-max-score", "0"], "--ref-min-score 'low': give a number"),
])
def test_cli_bad_reference_scores_exit_2(drift, monkeypatch, capsys, args, message):
    code, err = _drift_cli(drift, monkeypatch, capsys, *args)
    assert code == 2 and message in err, err
    assert not (drift / "runs" / "bad").exists()


# slow (~60 s): the metric's parts are tested one by one above, and the pendulum's summary, curve
# and table in the default suite
@pytest.mark.slow
@pytest.mark.timeout(600)
def test_cli_normalised_score_end_to_end(drift, monkeypatch, capsys):
    """--ref-min-score/--ref-max-score: config.json records the metric, summary.json has score_*
    = 100 (R - min) / (max - min) of its return_*, and `botorl eval` (the task given again with
    --env, its references from config.json) prints the score."""
    out = drift / "runs" / "score"
    code, err = _drift_cli(drift, monkeypatch, capsys, "--method", "wsrl", "--ref-min-score", "-40",
                           "--ref-max-score", "0", out=out)
    assert code == 0, err
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["metric"] == {"name": "score", "ref_min_score": -40.0, "ref_max_score": 0.0}
    s = json.loads((out / "summary.json").read_text())
    assert "success_initial" not in s and s["return_final"] < 0
    for p in ("initial", "final"):
        assert s[f"score_{p}"] == pytest.approx(100 * (s[f"return_{p}"] + 40) / 40)
    # another process, another folder: the task given again with --env (a run directory names no
    # code botorl imports, issue 39), its references read back from config.json
    env = _env()
    env["PYTHONPATH"] = str(drift) + os.pathsep + env["PYTHONPATH"]
    proc = subprocess.run([sys.executable, "-m", "botorl.cli", "eval", str(out), "--episodes", "2",
                           "--env", "drift:make_env"], cwd="/", env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert re.search(r"^score +", proc.stdout, re.M) and "success" not in proc.stdout, proc.stdout

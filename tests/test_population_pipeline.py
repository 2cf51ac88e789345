"""Populations through the real pipeline (`botorl run --seeds ... --alphas ...`, smoke profile).

- Independence: member (seed 3, alpha 0.5) of a 4-member population and a 1-member
  population (seed 3, alpha 0.5) draw the same warm-up actions and reach the same losses
  (rtol 1e-3: vmapped matmuls may sum in another order) at every logged point of >= 200
  updates of each stage (pre-training, BOTO, fine-tuning), and the same evaluations.
- Layout: each member an ordinary run directory; population.json; one population checkpoint.
- Bad input exits 2 before any work; a kill -9 inside pre-training and one inside
  fine-tuning each continue with `botorl resume POPDIR` for every member.
"""

from __future__ import annotations

import csv
import json
import math
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import subprocess_env as _env

from botorl.cli import main as botorl_main

TASK = "pointmaze-umaze"
# >= 200 updates of every stage: 200 pre-training steps, 200 BOTO steps, 200 fine-tuning
# steps after the 30-step warm-up
LONG = ["--offline.steps", "200", "--boto.boto_steps", "200", "--online.steps", "230", "--checkpoint_every", "1000",
        "--eval.interval", "115"]


def _run(out: Path, *args: str) -> int:
    return botorl_main(["run", "--task", TASK, "--profile", "smoke", "--no-progress", "--no-tensorboard",
                        "--out", str(out), *args])


def _csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def pops(tmp_path_factory):
    root = tmp_path_factory.mktemp("pop")
    assert _run(root / "four", "--seeds", "3,4", "--alphas=-0.5,0.5", *LONG) == 0
    assert _run(root / "one", "--seeds", "3", "--alphas", "0.5", *LONG) == 0
    return root / "four", root / "one"


def test_member_independent_of_its_population(pops):
    four, one = pops
    a, b = four / "alpha+0.50-seed3", one / "alpha+0.50-seed3"
    for d in (a, b):
        cfg = json.loads((d / "config.json").read_text())
        assert (cfg["seed"], cfg["alpha"]) == (3, 0.5) and not {"alpha", "seed"} & set(cfg["boto"])
    # the same warm-up (actions of the frozen stochastic policy, env transitions)
    w4 = np.load(four / "checkpoints" / "warmup-final" / "warmup-m2.npz")
    w1 = np.load(one / "checkpoints" / "warmup-final" / "warmup-m0.npz")
    np.testing.assert_allclose(w4["actions"], w1["actions"], atol=1e-5)
    np.testing.assert_allclose(w4["observations"], w1["observations"], atol=1e-4)
    counted = {}
    for stage in ("pretrain", "boto", "finetune"):
        ra, rb = _csv(a / "metrics" / f"{stage}.csv"), _csv(b / "metrics" / f"{stage}.csv")
        assert [r["step"] for r in ra] == [r["step"] for r in rb] and ra
        for x, y in zip(ra, rb):
            for k in ("critic_loss", "q_data", "actor_loss", "target", "penalty"):
                if k in x and x[k] not in ("", None):
                    assert math.isclose(float(x[k]), float(y[k]), rel_tol=1e-3, abs_tol=1e-4), (stage, x["step"], k)
        counted[stage] = int(float(ra[-1]["step"]))
    assert counted["pretrain"] >= 200 and counted["boto"] >= 200 and counted["finetune"] - 30 >= 200
    ea, eb = _csv(a / "eval.csv"), _csv(b / "eval.csv")
    assert [(r["stage"], r["env_step"], r["success"]) for r in ea] == [(r["stage"], r["env_step"], r["success"]) for r in eb]
    for x, y in zip(ea, eb):
        assert math.isclose(float(x["q_data"]), float(y["q_data"]), rel_tol=1e-3, abs_tol=1e-4)
    # another seed is another member
    other = _csv(four / "alpha+0.50-seed4" / "metrics" / "pretrain.csv")
    assert other[-1]["critic_loss"] != _csv(a / "metrics" / "pretrain.csv")[-1]["critic_loss"]


def test_population_layout(pops):
    four, _ = pops
    pop = json.loads((four / "population.json").read_text())
    assert pop["status"] == "finished" and [m["name"] for m in pop["members"]] == [
        "alpha-0.50-seed3", "alpha-0.50-seed4", "alpha+0.50-seed3", "alpha+0.50-seed4"]
    assert (four / "checkpoints" / "finetune-final" / "agent.ckpt").exists()
    for m in pop["members"]:
        d = four / m["name"]
        s = json.loads((d / "summary.json").read_text())
        assert s["status"] == "finished" and (s["seed"], s["alpha"]) == (m["seed"], m["alpha"])
        assert (d / "curve.png").exists() and (d / "checkpoints" / "finetune-final" / "agent.ckpt").exists()
    # `botorl eval` reads a member's run directory as any run's
    assert botorl_main(["eval", str(four / "alpha-0.50-seed4"), "--episodes", "1"]) == 0


@pytest.mark.parametrize("args, message", [
    (["--seeds", "0,1,1"], "given twice"),
    (["--seeds", "0-1", "--alphas=0.5,1.5"], "outside [-1, 1]"),
    (["--seeds", "0-1", "--alphas=0.5,0.5"], "given twice"),
    (["--method", "wsrl", "--seeds", "0-1", "--alphas", "0.5"], "no BOTO phase"),
    (["--seeds", "0-63", "--online.buffer_capacity", "1000000000"], "fewer members"),
])
def test_bad_population_exit_2(tmp_path, capsys, args, message):
    out = tmp_path / "bad"
    assert _run(out, *args) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.slow
@pytest.mark.parametrize("method", ["calql", "cql", "iql", "rlpd", "wsrl"])
def test_every_method_as_a_population(tmp_path, method):
    """Each method trains as a population of 2 (boto: the fixture above). Cal-QL online
    updates a member only once its first episode has ended (masked batched updates)."""
    out = tmp_path / method
    assert _run(out, "--method", method, "--seeds", "0,1", "--online.steps", "120") == 0
    for name in ("seed0", "seed1"):
        s = json.loads((out / name / "summary.json").read_text())
        assert s["status"] == "finished" and s["method"] == method
        assert _csv(out / name / "metrics" / "finetune.csv")


# slow (~65 s): test_pipeline_run's dense-window test runs two arms over one pre-training in the
# default suite
@pytest.mark.slow
@pytest.mark.timeout(900)
def test_alphas_of_one_seed_share_one_pretraining(tmp_path, monkeypatch):
    """BOTO at two alphas from one seed pre-trains once (one agent in every pre-training call
    and in the mid-stage checkpoint); both members get that agent. A kill -9 inside the shared
    pre-training, and another inside fine-tuning, each resumed with `botorl resume POPDIR`,
    end every member at the numbers of the uninterrupted run, each step logged once."""
    from botorl.agents import population as AP

    sizes = []
    real = AP.update_many

    def counting(agents, batches):
        sizes.append(AP.population_size(agents))
        return real(agents, batches)

    monkeypatch.setattr(AP, "update_many", counting)
    args = ["--seeds", "0", "--alphas=-0.5,0.5", "--offline.steps", "20", "--online.steps", "80",
            "--checkpoint_every", "10"]
    whole = tmp_path / "whole"
    assert _run(whole, *args) == 0
    assert sizes and set(sizes) == {1}  # pre-training's calls, one agent for both members
    pre = [_csv(whole / m / "metrics" / "pretrain.csv") for m in ("alpha-0.50-seed0", "alpha+0.50-seed0")]
    assert pre[0] == pre[1] and pre[0]

    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "botorl.cli", "run", "--task", TASK, "--profile", "smoke", "--no-progress",
           "--no-tensorboard", *args, "--out", str(out)]
    proc = subprocess.run(cmd, env={**_env(), "BOTORL_KILL_AT": "pretrain:10"}, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    assert json.loads((out / "checkpoints" / "latest.json").read_text())["stage"] == "pretrain"
    resume = [sys.executable, "-m", "botorl.cli", "resume", str(out), "--no-progress"]
    res = subprocess.run(resume, env={**_env(), "BOTORL_KILL_AT": "finetune:57"}, capture_output=True, text=True,
                         timeout=600)
    assert res.returncode == -signal.SIGKILL, res.stderr[-2000:]
    assert "from pretrain step 10" in res.stderr
    assert json.loads((out / "checkpoints" / "latest.json").read_text())["stage"] == "finetune"
    assert json.loads((out / "population.json").read_text())["status"] == "running"
    res = subprocess.run(resume, env=_env(), capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert f"resuming {out} from finetune step 50" in res.stderr
    assert json.loads((out / "population.json").read_text())["status"] == "finished"
    for m in ("alpha-0.50-seed0", "alpha+0.50-seed0"):
        assert json.loads((out / m / "summary.json").read_text())["status"] == "finished"
        for log in ("pretrain.csv", "boto.csv", "finetune.csv"):
            assert [r["step"] for r in _csv(out / m / "metrics" / log)] == \
                [r["step"] for r in _csv(whole / m / "metrics" / log)], f"{m}: metrics/{log}"
        a, b = _csv(whole / m / "eval.csv"), _csv(out / m / "eval.csv")
        assert [(r["env_step"], r["success"], r["return"]) for r in a] == [(r["env_step"], r["success"], r["return"]) for r in b]
        for x, y in zip(a, b):
            assert math.isclose(float(x["q_data"]), float(y["q_data"]), rel_tol=1e-6, abs_tol=1e-6)


def test_wsrl_starts_from_botos_pretraining(pops, tmp_path, monkeypatch):
    """`--pretrained DIR`: WSRL at seed 3 takes the BOTO population's pre-trained seed-3 agent
    (no pre-training update runs) and so collects the same warm-up and scores the same step-0
    evaluation as the BOTO member of that seed; its pre-training logs are the source's."""
    from botorl.agents import population as AP

    four, _ = pops
    calls = []
    monkeypatch.setattr(AP, "update_many", lambda *a: calls.append(1))
    out = tmp_path / "wsrl"
    assert _run(out, "--method", "wsrl", "--seeds", "3", "--pretrained", str(four), *LONG) == 0
    assert not calls
    src, member = four / "alpha+0.50-seed3", out / "seed3"
    assert json.loads((member / "config.json").read_text())["pretrained"] == str(four)
    assert _csv(member / "metrics" / "pretrain.csv") == _csv(src / "metrics" / "pretrain.csv")
    w_src = np.load(four / "checkpoints" / "warmup-final" / "warmup-m2.npz")
    w_new = np.load(out / "checkpoints" / "warmup-final" / "warmup-m0.npz")
    np.testing.assert_allclose(w_src["actions"], w_new["actions"], atol=1e-5)  # vmapped over 4 vs 1: float order
    e_src, e_new = _csv(src / "eval.csv")[0], _csv(member / "eval.csv")[0]
    assert (e_src["stage"], e_src["env_step"]) == (e_new["stage"], e_new["env_step"]) == ("warmup", "0")
    assert e_src["success"] == e_new["success"]
    assert math.isclose(float(e_src["q_data"]), float(e_new["q_data"]), rel_tol=1e-4)
    assert _csv(member / "metrics" / "finetune.csv")


@pytest.mark.parametrize("args, message", [
    (["--method", "wsrl", "--seeds", "3,5"], "at seed 5"),
    (["--method", "wsrl", "--seed", "3", "--offline.steps", "100"], "offline.steps (200 there, 100 here)"),
    (["--method", "rlpd", "--seed", "3"], "no pre-training to skip"),
])
def test_pretrained_mismatch_exit_2(pops, tmp_path, capsys, args, message):
    four, _ = pops
    long = LONG[2:] if "--offline.steps" in args else LONG
    out = tmp_path / "bad"
    assert _run(out, *args, "--pretrained", str(four), *long) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()

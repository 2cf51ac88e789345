"""botorl study: the study file's checks (exit 2 naming the field), the frozen-commit check, a
study run end to end (killed mid-arm, resumed, reported: the same numbers as an uninterrupted
run), the pre-training digest check, and the legacy blocks of study 1 (paired.csv rows mapped to
arms by their resolved configs; its pooled numbers recomputed)."""

from __future__ import annotations

import csv
import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from botorl.cli import main as cli
from botorl.errors import ConfigError
from botorl.experiments import study as study_mod
from botorl.experiments.pairs import QUANTITIES, Pair, pairs_csv
from botorl.experiments.study import frozen_deviation, load_study
from botorl.experiments.study_report import Records, analyse, report

ROOT = Path(__file__).resolve().parents[1]

SMOKE = """\
[study]
name = "smoke"
question = "Does the smoke study run, resume and report?"
commit = "{commit}"
tasks = ["pointmaze-umaze"]
profile = "smoke"
population_size = {size}
runs = "{runs}"
reference = "a"

[[blocks]]
name = "b0"
seeds = "0-1"

[[blocks]]
name = "b1"
seeds = "2-3"

[[arms]]
key = "b"
label = "BOTO"
method = "boto"
alpha = -1.0
pretrains = true

[[arms]]
key = "a"
label = "WSRL"
method = "wsrl"
reuses = "b"

[[arms]]
key = "d"
label = "re-fit control"
method = "boto"
alpha = -1.0
set = ["boto.noise=none"]
reuses = "b"

[analysis]
endpoints = ["dip", "window_mean", "success_final"]
primary = ["b-a", "d-a"]
secondary = ["b-d"]
floors = []
equivalence = {{ "b-d" = 0.5 }}
window_end = 40
n_boot = 200
"""

TWO_ARMS = """\
[[blocks]]
name = "b0"
seeds = "0"

[[arms]]
key = "b"
method = "boto"
pretrains = true

[[arms]]
key = "a"
method = "wsrl"
reuses = "b"
"""

# A stand-in for `python -m botorl.cli` in the sweeps (their --trial-command): a "run" writes
# config.json, sleeps (so that a kill lands mid-arm), then eval.csv and summary.json with numbers
# fixed by the arm's settings and the seed, and the pre-training digest of the seed.
STANDIN = textwrap.dedent('''
    import hashlib, json, os, random, sys, time
    from pathlib import Path
    argv = sys.argv[1:]
    if argv[0] == "run":
        out = Path(argv[argv.index("--out") + 1])
        cfg = json.loads(Path(argv[argv.index("--config") + 1]).read_text())
        cfg["environment"] = {"commit": "standin"}
        out.mkdir(parents=True, exist_ok=True)
        (out / "config.json").write_text(json.dumps(cfg))
    else:
        out = Path(argv[1])
        cfg = json.loads((out / "config.json").read_text())
    time.sleep(float(os.environ.get("STANDIN_SLEEP", "0.3")))
    key = [cfg["task"], cfg["seed"], cfg["method"], cfg["alpha"], cfg["boto"]["noise"], cfg["online_reseed"]]
    rng = random.Random(json.dumps(key))
    salt = os.environ.get("STANDIN_SALT_METHOD") == cfg["method"]
    sha = hashlib.sha256(f"{cfg['task']}{cfg['seed']}{salt}".encode()).hexdigest()
    rows = ["stage,env_step,success,return,q_data,q_uniform", f"warmup,0,1,0,{cfg['seed']},{-cfg['seed']}",
            f"finetune,30,{rng.random():.3f},0,{rng.random():.3f},{rng.random():.3f}"]
    rows += [f"finetune,{s},{rng.choice([0, 0.5, 1])},0,0,0" for s in (10, 20, 40)]
    (out / "eval.csv").write_text("\\n".join(rows) + "\\n")
    (out / "summary.json").write_text(json.dumps({"status": "finished", "task": cfg["task"], "method": cfg["method"],
                                                  "alpha": cfg["alpha"], "seed": cfg["seed"], "pretrain_sha256": sha}))
''')


def _write(tmp_path: Path, text: str, name: str = "study.toml") -> Path:
    path = tmp_path / "plan" / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def _smoke(tmp_path: Path, runs: str = "runs", size: int = 1) -> Path:
    return _write(tmp_path, SMOKE.format(commit="0123abc", size=size, runs=tmp_path / runs))


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
            "JAX_PLATFORMS": "cpu"}


def _study(args: list[str], tmp_path: Path, **env: str) -> subprocess.Popen:
    """`botorl study ...` in its own process group (so that a test can kill -9 all of it)."""
    return subprocess.Popen([sys.executable, "-m", "botorl.cli", "study", *args], cwd=tmp_path, env=_env() | env,
                            start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


# ----------------------------------------------------------------------------- the file's checks

BAD = [
    ("unknown arm", ('primary = ["b-a", "d-a"]', 'primary = ["b-z"]'), "primary"),
    ("overlapping blocks", ('seeds = "2-3"', 'seeds = "1-3"'), "seeds"),
    ("reuses no pre-training", ('reuses = "b"\n\n[[arms]]\nkey = "d"', 'reuses = "a"\n\n[[arms]]\nkey = "d"'),
     "reuses 'a'"),
    ("missing commit", ('commit = "0123abc"\n', ''), "commit is missing"),
    ("bad commit", ('commit = "0123abc"', 'commit = "main"'), "commit"),
    ("unknown endpoint", ('"window_mean"', '"auc"'), "endpoints"),
    ("bad TOML", ('[analysis]', '[analysis'), "not valid TOML"),
    ("unknown field", ('profile = "smoke"', 'profile = "smoke"\nprofiel = "quick"'), "profiel"),
    ("unknown method", ('method = "wsrl"', 'method = "wsrll"'), "method"),
    ("alpha off boto", ('method = "wsrl"', 'method = "wsrl"\nalpha = 1.0'), "alpha"),
    ("both pretrains and reuses", ('reuses = "b"\n\n[[arms]]\nkey = "d"', 'reuses = "b"\npretrains = true\n\n[[arms]]\nkey = "d"'),
     "pretrains"),
    ("equivalence of no comparison", ('{ "b-d" = 0.5 }', '{ "a-d" = 0.5 }'), "equivalence"),
    ("reference no arm", ('reference = "a"', 'reference = "w"'), "reference"),
    ("seeds as text", ('seeds = "0-1"', 'seeds = "zero"'), "seeds"),
]


@pytest.mark.parametrize("case,edit,field", BAD, ids=[b[0] for b in BAD])
def test_a_bad_study_file_exits_2_naming_the_field(tmp_path, capsys, case, edit, field):
    good = _smoke(tmp_path).read_text()
    assert edit[0] in good, case
    path = _write(tmp_path, good.replace(edit[0], edit[1], 1), "bad.toml")
    with pytest.raises(ConfigError, match="bad.toml") as err:
        load_study(path)
    assert field in str(err.value), str(err.value)
    assert cli(["study", "report", str(path)]) == 2  # the command: exit 2, a message, no traceback
    assert field in capsys.readouterr().err


def test_seeds_of_a_wrong_type_are_said_once(tmp_path):
    # the type's message on its own, not nested inside "is not a seed set (...)"
    good = _smoke(tmp_path).read_text()
    path = _write(tmp_path, good.replace('seeds = "0-1"', "seeds = 1.5", 1), "bad.toml")
    with pytest.raises(ConfigError) as err:
        load_study(path)
    text = str(err.value)
    assert "seeds must be text or a whole number or a list, got 1.5" in text
    assert "not a seed set" not in text and text.count("bad.toml") == 1


def test_the_commit_must_be_the_frozen_one(tmp_path, monkeypatch, capsys):
    s = load_study(_smoke(tmp_path))
    assert frozen_deviation(s, "0123abc" + "f" * 33) is None
    assert "uncommitted" in frozen_deviation(s, "0123abc" + "f" * 33 + "+dirty")
    assert "is at commit 4567" in frozen_deviation(s, "4567" + "f" * 36)
    assert "cannot be read" in frozen_deviation(s, None)
    monkeypatch.setattr(study_mod, "botorl_commit", lambda: "4567" + "f" * 36)
    assert cli(["study", "run", str(s.path)]) == 2
    err = capsys.readouterr().err
    assert "frozen at 0123abc" in err and "--unfrozen" in err
    assert not (tmp_path / "runs").exists()  # refused before anything ran


# ----------------------------------------------------------------------------- a study end to end

def _records_of(results: Path) -> dict[str, str]:
    """The records' contents but config.json, which names the folders the runs were made in."""
    return {str(p.relative_to(results)): p.read_text() for p in sorted(results.rglob("*"))
            if p.name in ("summary.json", "eval.csv")}


def test_a_study_killed_mid_arm_resumes_and_reports_what_an_uninterrupted_one_does(tmp_path):
    standin = tmp_path / "standin.py"
    standin.write_text(STANDIN)
    trial = ["--trial-command", f"{sys.executable} {standin}", "--unfrozen"]
    plan = _smoke(tmp_path)
    # kill -9 the whole study (its sweeps and trials) once the second arm has a trial running
    proc = _study(["run", str(plan), *trial], tmp_path)
    second = tmp_path / "runs" / "b0" / "a"
    deadline = time.time() + 120
    while not any(second.rglob("config.json")) and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    assert proc.poll() is None, proc.communicate()[0].decode()
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    state = json.loads((plan.parent / "results" / study_mod.STATE).read_text())
    assert state["arms"]["b0/b"]["ended"] and not state["arms"]["b0/a"].get("ended")
    # the same command continues (two lanes now) and finishes
    again = _study(["run", str(plan), "--lanes", "2", *trial], tmp_path)
    out = again.communicate(timeout=300)[0].decode()
    assert again.returncode == 0, out
    state = json.loads((plan.parent / "results" / study_mod.STATE).read_text())
    assert len(state["invocations"]) == 2 and all(i["unfrozen"] for i in state["invocations"])
    assert all(state["arms"][f"{b}/{a}"]["runs"] == 2 for b in ("b0", "b1") for a in ("b", "a", "d"))
    results = plan.parent / "results"
    assert sorted(p.name for p in (results / "b1" / "d" / "pointmaze-umaze" / "seed3").iterdir()) == [
        "config.json", "eval.csv", "summary.json"]
    # the report reads the records alone: the run directories are gone
    os.rename(tmp_path / "runs", tmp_path / "runs-gone")
    assert cli(["study", "report", str(plan)]) == 0
    analysis = plan.parent / "analysis"
    text = (analysis / "analysis.md").read_text()
    assert "Primary comparisons (6 tests, Holm)" in text and "--unfrozen" in text and "not the frozen commit" in text
    assert "Manipulation check" in text and (analysis / "b0" / "report.md").is_file()
    assert "botorl sweep --tasks pointmaze-umaze --profile smoke --methods wsrl --seeds 2-3" in (
        analysis / "commands.sh").read_text()
    rows = list(csv.DictReader((analysis / "comparisons.csv").open()))
    assert {r["comparison"] for r in rows if r["kind"] == "primary"} == {"b-a", "d-a"}
    assert all(r["n"] == "4" for r in rows)
    # an uninterrupted twin in another folder: the same records, so the same numbers
    twin = _write(tmp_path / "twin", SMOKE.format(commit="0123abc", size=1, runs=tmp_path / "twin-runs"))
    done = _study(["run", str(twin), "--lanes", "3", *trial], tmp_path)
    assert done.wait(timeout=300) == 0, done.communicate()[0].decode()
    assert cli(["study", "report", str(twin)]) == 0
    assert _records_of(results) == _records_of(twin.parent / "results")
    for name in ("comparisons.csv", "arms.csv"):
        assert (analysis / name).read_text() == (twin.parent / "analysis" / name).read_text()


def test_an_arm_from_another_pre_training_is_refused(tmp_path):
    standin = tmp_path / "standin.py"
    standin.write_text(STANDIN)
    plan = _write(tmp_path, SMOKE.split("[[blocks]]")[0].format(commit="0123abc", size=1, runs=tmp_path / "runs")
                  + TWO_ARMS)
    proc = _study(["run", str(plan), "--trial-command", f"{sys.executable} {standin}", "--unfrozen"], tmp_path,
                  STANDIN_SALT_METHOD="wsrl", STANDIN_SLEEP="0")
    out = proc.communicate(timeout=300)[0].decode()
    assert proc.returncode == 2, out
    assert "b0/a" in out and "do not start from the pre-training of arm 'b'" in out and "Traceback" not in out


@pytest.mark.slow
def test_a_real_smoke_study_killed_mid_arm_resumes_and_reports(tmp_path):
    """The real `botorl run`s (smoke profile, populations): a kill -9 during block b0's second
    arm, then the same command; every arm of a block starts from one pre-training."""
    plan = _smoke(tmp_path, size=2)
    proc = _study(["run", str(plan), "--unfrozen"], tmp_path)
    second = tmp_path / "runs" / "b0" / "a"
    deadline = time.time() + 900
    while not any(second.rglob("sweep-trial.log")) and time.time() < deadline and proc.poll() is None:
        time.sleep(0.2)
    time.sleep(3)
    assert proc.poll() is None, proc.communicate()[0].decode()
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    again = _study(["run", str(plan), "--unfrozen"], tmp_path)
    out = again.communicate(timeout=1800)[0].decode()
    assert again.returncode == 0, out
    state = json.loads((plan.parent / "results" / study_mod.STATE).read_text())
    for block in ("b0", "b1"):
        digests = [state["arms"][f"{block}/{a}"]["pretrain_sha256"] for a in ("b", "a", "d")]
        assert digests[0] == digests[1] == digests[2] and all(digests[0].values())
    assert cli(["study", "report", str(plan)]) == 0
    rows = list(csv.DictReader((plan.parent / "analysis" / "comparisons.csv").open()))
    assert all(r["n"] == "4" for r in rows if r["kind"] != "manipulation")


# ----------------------------------------------------------------------------- legacy blocks

def _pair(seed, label, alpha, dip, s10k, ref_dip=-1.0):
    ref = {q: 1.0 for q in QUANTITIES} | {"dip": ref_dip, "lowest": 1.0 + ref_dip, "success_10k": 0.5}
    other = {q: 1.0 for q in QUANTITIES} | {"dip": dip, "lowest": 1.0 + dip, "success_10k": s10k}
    return Pair("pointmaze-medium", seed, label, alpha, "wsrl", ref, other)


# the variant keys of a report in which (e) ran too: its labels tell (b) from (e)
B = 'boto+calql [boto.backup_entropy=true, boto.noise="hybrid"]'
D = 'boto+calql [boto.backup_entropy=true, boto.noise="none"]'
F2 = 'boto+calql [boto.backup_entropy=true, boto.noise="hybrid", online_reseed=1]'


def test_legacy_rows_map_to_arms_by_their_configs_and_pair_within_a_block(tmp_path):
    text = (ROOT / "docs" / "results" / "why-boto" / "study.toml").read_text()
    text = text.replace('seeds = "200-207"', 'seeds = "0-1"').replace('seeds = "208-215"', 'seeds = "2-3"')
    plan = _write(tmp_path, text.replace('seeds = "216-223"\npaired_csv = "b2/paired.csv"', 'seeds = "4-5"'))
    b0, b1 = plan.parent / "b0" / "paired.csv", plan.parent / "b1" / "paired.csv"
    b0.parent.mkdir()
    b1.parent.mkdir()
    b0.write_text(pairs_csv([_pair(0, B, -1.0, -0.2, 1.0), _pair(0, D, -1.0, -0.5, 1.0), _pair(0, F2, -1.0, -0.4, 1.0),
                             _pair(1, B, -1.0, -1.0, 0.5), _pair(1, D, -1.0, -0.8, 0.0),
                             _pair(1, "wsrl [online_reseed=1]", None, -0.9, 0.5),
                             _pair(1, B, 0.0, 0.0, 1.0)]))  # alpha 0: a run of no arm
    # block b1's seed 0 is another pre-training: it must not pair with block b0's
    b1.write_text(pairs_csv([_pair(0, D, -1.0, 0.0, 1.0, ref_dip=-0.5)]))
    rec = Records(load_study(plan))
    assert ("b0", "c", "pointmaze-medium", 1) not in rec.values and ("b1", "b", "pointmaze-medium", 0) not in rec.values
    np.testing.assert_allclose(rec.differences("b", "d", "dip")[0], [-0.2 - -0.5, -1.0 - -0.8])
    vals, blocks = rec.differences("d", "a", "dip")
    np.testing.assert_allclose(vals, [-0.5 - -1.0, -0.8 - -1.0, 0.0 - -0.5])
    assert blocks == ["b0", "b0", "b1"]
    np.testing.assert_allclose(rec.differences("f2", "b", "dip")[0], [-0.4 - -0.2])
    np.testing.assert_allclose(rec.differences("f1", "a", "success_10k")[0], [0.0])
    assert any("1 row(s)" in n for n in rec.notes)  # the alpha-0 row
    res = analyse(rec)
    bd = next(r for r in res["primary"] if r["endpoint"] == "dip" and r["comparison"] == "b-d")
    assert bd["n"] == 2 and math.isclose(bd["mean"], 0.05) and (bd["better"], bd["equal"], bd["worse"]) == (1, 0, 1)
    da = next(r for r in res["primary"] if r["endpoint"] == "dip" and r["comparison"] == "d-a")
    assert da["block_range"] == (0.35, 0.5) and da["block_means"] == [("b0", 0.35), ("b1", 0.5)]
    assert [r["n"] for r in res["floors"]] == [1, 1, 1, 1]


def test_study_1_reproduces_its_pooled_numbers(tmp_path):
    """The committed paired.csv files through the study file: the page's means and bootstrap CIs
    (10,000 resamples, seed 0) and the plan's Wilcoxon (normal with ties) under Holm."""
    rec = Records(load_study(ROOT / "docs" / "results" / "why-boto" / "study.toml"))
    res = analyse(rec)
    dip = {r["comparison"]: r for r in res["primary"] if r["endpoint"] == "dip"}
    assert {c: r["n"] for c, r in dip.items()} == dict.fromkeys(["b-a", "c-a", "d-a", "e-a", "b-d"], 24)
    assert [round(dip[c]["mean"], 2) for c in ("b-a", "c-a", "d-a", "e-a", "b-d")] == [0.30, 0.33, 0.28, 0.19, 0.02]
    assert [round(x, 2) for x in dip["b-a"]["boot"]] == [0.14, 0.47]
    assert [round(x, 2) for x in dip["b-d"]["boot"]] == [-0.16, 0.20]
    assert (dip["b-d"]["better"], dip["b-d"]["equal"], dip["b-d"]["worse"]) == (5, 11, 8)
    assert [round(dip[c]["p_holm"], 3) for c in ("b-a", "c-a", "d-a")] == [0.041, 0.030, 0.041]
    assert all(r["method"] == "normal" for r in res["primary"])
    assert [round(x, 2) for x in dip["e-a"]["block_range"]] == [0.16, 0.23]
    floor = next(r for r in res["floors"] if r["endpoint"] == "dip" and r["comparison"] == "f2-b")
    assert round(floor["sd"], 2) == 0.45 and [round(x, 2) for x in floor["spread"]] == [-0.80, 0.97]


def _record(folder: Path, method: str, seed: int, sha: str, success: list[float], q_after: float) -> None:
    """A run's three records by hand: evaluations at steps 0 (the warm-up's), 30 (fine-tuning's
    first) and 10, 20, 40."""
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps({"task": "pointmaze-umaze", "method": method, "seed": seed,
                                                    "environment": {"commit": "0123abc" + "0" * 33}}))
    (folder / "summary.json").write_text(json.dumps({"status": "finished", "task": "pointmaze-umaze", "method": method,
                                                     "seed": seed, "alpha": None, "pretrain_sha256": sha * 64}))
    rows = ["stage,env_step,success,return,q_data,q_uniform", "warmup,0,1,0,2.0,1.0",
            f"finetune,30,{success[2]},0,{q_after},{q_after / 2}"]
    rows += [f"finetune,{s},{v},0,0,0" for s, v in zip((10, 20, 40), (success[0], success[1], success[3]))]
    (folder / "eval.csv").write_text("\n".join(rows) + "\n")


def test_the_report_reads_records_by_hand_and_pairs_only_one_pre_training(tmp_path):
    plan = _write(tmp_path, SMOKE.split("[[blocks]]")[0].format(commit="0123abc", size=1, runs=tmp_path / "runs")
                  + TWO_ARMS.replace('seeds = "0"', 'seeds = "0-1"')
                  + '[analysis]\nendpoints = ["dip", "window_mean"]\nprimary = ["b-a"]\nwindow_end = 30\n')
    results = plan.parent / "results" / "b0"
    _record(results / "b" / "pointmaze-umaze" / "seed0", "boto", 0, "a", [0.5, 1.0, 0.5, 1.0], 4.0)
    _record(results / "a" / "pointmaze-umaze" / "seed0", "wsrl", 0, "a", [0.0, 0.0, 1.0, 1.0], 2.0)
    _record(results / "b" / "pointmaze-umaze" / "seed1", "boto", 1, "b", [1.0, 1.0, 1.0, 1.0], 2.0)
    _record(results / "a" / "pointmaze-umaze" / "seed1", "wsrl", 1, "c", [0.0, 0.0, 0.0, 0.0], 2.0)
    rec = Records(load_study(plan))
    # seed 0: dip over steps 0..30 is min(1, .5, 1, .5) - 1 = -0.5 against min(1, 0, 0, 1) - 1 = -1
    assert rec.differences("b", "a", "dip") == ([0.5], ["b0"])
    # window_mean: evaluations after 0 up to 30: (0.5 + 1 + 0.5) / 3 against (0 + 0 + 1) / 3
    np.testing.assert_allclose(rec.differences("b", "a", "window_mean")[0], [1 / 3])
    np.testing.assert_allclose(rec.differences("b", "a", "q_uniform_change")[0], [1.0])  # (4 - 2) / 2 - (1 - 1)
    assert len(rec.unpaired) == 1  # seed 1: two pre-trainings, never a pair
    assert rec.commits == {"0123abc" + "0" * 33: 4}
    assert cli(["study", "report", str(plan)]) == 0
    text = (plan.parent / "analysis" / "analysis.md").read_text()
    assert "not paired: b0/b/pointmaze-umaze/1 and b0/a/pointmaze-umaze/1" in text and "not the frozen" not in text
    assert "| Q change, uniform actions | (b) b − (a) a | 1 | +1.00 |" in text  # the manipulation check


def test_a_study_without_comparisons_reports_no_figure(tmp_path):
    # a descriptive study (arms, no comparison): nothing to plot, so no figure listed or linked
    plan = _write(tmp_path, SMOKE.split("[[blocks]]")[0].format(commit="0123abc", size=1, runs=tmp_path / "runs")
                  + TWO_ARMS + '[analysis]\nendpoints = ["dip"]\nwindow_end = 30\n')
    results = plan.parent / "results" / "b0"
    _record(results / "b" / "pointmaze-umaze" / "seed0", "boto", 0, "a", [0.5, 1.0, 0.5, 1.0], 4.0)
    _record(results / "a" / "pointmaze-umaze" / "seed0", "wsrl", 0, "a", [0.0, 0.0, 1.0, 1.0], 2.0)
    files = report(load_study(plan), plan.parent / "analysis")
    assert [f.name for f in files if f.suffix == ".png"] == []
    assert not (plan.parent / "analysis" / "paired_differences.png").exists()
    assert "paired_differences.png" not in (plan.parent / "analysis" / "analysis.md").read_text()

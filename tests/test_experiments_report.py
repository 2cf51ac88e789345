"""botorl report: exact statistics from run directories written by hand, figures, alpha selection."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from botorl.experiments import report as R
from botorl.experiments.cli import report_main


def write_run(
    root: Path,
    *,
    task: str,
    method: str,
    seed: int,
    initial: float,
    s10k: float,
    final: float,
    alpha: float | None = None,
    pretrain: str | None = None,
    status: str = "finished",
    curve: list[tuple[int, float]] | None = None,
    extra_rows: list[str] = (),
) -> Path:
    d = root / task / method / (f"alpha{alpha:+.2f}" if alpha is not None else "") / f"seed{seed}"
    d.mkdir(parents=True)
    meta = {"task": task, "method": method, "seed": seed, "alpha": alpha, "pretrain": pretrain, "profile": "quick"}
    (d / "config.json").write_text(json.dumps(meta))
    summary = dict(meta, success_initial=initial, success_10k=s10k, success_final=final,
                   stage_seconds={"online": 1.0}, status=status)
    (d / "summary.json").write_text(json.dumps(summary))
    rows = curve if curve is not None else [(0, initial), (10000, s10k), (20000, final)]
    with open(d / "eval.csv", "w") as f:
        f.write("stage,env_step,success,return,q_data,q_uniform\n")
        for row in extra_rows:
            f.write(row + "\n")
        for step, succ in rows:
            f.write(f"online,{step},{succ},0,0,0\n")
    return d


# Hand-made numbers. wsrl on t1: 4 seeds.
WSRL_INITIAL = [0.1, 0.2, 0.3, 0.6]  # mean 0.3; squared deviations .04+.01+0+.09 = .14
WSRL_10K = [0.0, 0.5, 0.5, 1.0]  # mean 0.5; .25+0+0+.25 = .5
WSRL_FINAL = [1.0, 0.8, 0.9, 0.7]  # mean 0.85; .0225+.0025+.0025+.0225 = .05
# calql on t1: 5 seeds; final IQM by hand: sorted [0, .1, .2, .9, 1], cut floor(5/4)=1 each end
CALQL_FINAL = [0.9, 0.0, 1.0, 0.2, 0.1]  # IQM = (0.1 + 0.2 + 0.9) / 3 = 0.4


@pytest.fixture(scope="module")
def runs_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("runs")
    for seed in range(4):
        write_run(root, task="t1", method="wsrl", seed=seed, initial=WSRL_INITIAL[seed],
                  s10k=WSRL_10K[seed], final=WSRL_FINAL[seed],
                  # a second evaluation at step 0 from an earlier stage: the later row counts
                  extra_rows=["pretrain,0,0.99,0,0,0"])
    for seed in range(5):
        write_run(root, task="t1", method="calql", seed=seed, initial=0.5, s10k=0.1, final=CALQL_FINAL[seed])
    # wsrl on t2, 2 seeds, for the across-task aggregate
    for seed, v in enumerate([0.0, 1.0]):
        write_run(root, task="t2", method="wsrl", seed=seed, initial=v, s10k=v, final=v)
    # an alpha sweep of boto+calql on t1: score (10k + final)/2 per alpha
    #   -0.5 -> 0.6,  0.0 -> (0.4+1.0)/2 = 0.7,  0.5 -> (0.6+0.8)/2 = 0.7000000000000001 (a tie)
    sweep = {-0.5: (0.2, 1.0), 0.0: (0.4, 1.0), 0.5: (0.6, 0.8)}
    for alpha, (s10k, final) in sweep.items():
        for seed in range(2):
            write_run(root, task="t1", method="boto", pretrain="calql", alpha=alpha, seed=seed,
                      initial=0.3, s10k=s10k, final=final)
    # not finished: must be listed as skipped, with the reason
    write_run(root, task="t1", method="rlpd", seed=0, initial=0, s10k=0, final=0, status="running")
    write_run(root, task="t1", method="rlpd", seed=1, initial=0, s10k=0, final=0, status="failed")
    never = root / "t1" / "rlpd" / "seed3"  # `botorl run` failed before making the run directory
    never.mkdir(parents=True)
    (never / "sweep-trial.log").write_text("===== attempt 1\nbotorl run: error: dataset not found\n")
    crashed = root / "t1" / "rlpd" / "seed2"
    (crashed / "checkpoints").mkdir(parents=True)
    (crashed / "config.json").write_text(json.dumps({"task": "t1", "method": "rlpd", "seed": 2}))
    return root


def test_statistics_by_hand():
    mean, se, n = R.mean_se(WSRL_INITIAL)
    assert n == 4
    assert mean == pytest.approx(0.3, abs=1e-12)
    assert se == pytest.approx(math.sqrt(0.14 / 3) / 2, abs=1e-12)
    assert math.isnan(R.mean_se([0.5])[1])  # SE of one seed is undefined, not 0
    assert R.iqm(CALQL_FINAL) == pytest.approx(0.4, abs=1e-12)
    assert R.iqm([3.0, 1.0, 2.0, 10.0]) == pytest.approx(2.5, abs=1e-12)  # cut 1 each end
    assert R.iqm([5.0, 1.0, 2.0]) == pytest.approx(8.0 / 3, abs=1e-12)  # n < 4 cuts nothing
    # IQM over tasks pools the runs: 10 scores, cut 2 each end, mean of the middle 6
    t1, t2 = [0.0, 0.1, 0.2, 0.9, 1.0], [0.3, 0.3, 0.5, 0.6, 0.7]
    point, lo, hi = R.stratified_bootstrap_iqm([t1, t2], n_boot=500, seed=1)
    assert point == pytest.approx((0.2 + 0.3 + 0.3 + 0.5 + 0.6 + 0.7) / 6, abs=1e-12)
    assert lo <= point <= hi and hi - lo > 0.05
    # stratified: each task keeps its number of runs, so one run per task never varies
    point, lo, hi = R.stratified_bootstrap_iqm([[0.0], [1.0]], n_boot=300, seed=0)
    assert (point, lo, hi) == (0.5, 0.5, 0.5)


def test_report_tables_exact(runs_dir, tmp_path):
    out = tmp_path / "rep"
    result = R.make_report([runs_dir], out, n_boot=300, seed=0)
    assert len(result.runs) == 4 + 5 + 2 + 6
    reasons = {s.path.name: s.reason for s in result.skipped}
    assert len(result.skipped) == 4
    assert "running" in reasons["seed0"] and "failed" in reasons["seed1"]
    assert "no summary.json" in reasons["seed2"]
    assert reasons["seed3"].endswith("botorl run: error: dataset not found")

    with open(out / "table1.csv", newline="") as f:
        rows = {(r["task"], r["method"], r["alpha"]): r for r in csv.DictReader(f)}
    w = rows[("t1", "wsrl", "")]
    assert int(w["initial_n"]) == 4 and w["seeds"] == "0 1 2 3"
    for point, vals, mean, ss in (("initial", WSRL_INITIAL, 0.3, 0.14), ("10k", WSRL_10K, 0.5, 0.5),
                                  ("final", WSRL_FINAL, 0.85, 0.05)):
        assert float(w[f"{point}_mean"]) == pytest.approx(mean, abs=1e-12)
        assert float(w[f"{point}_se"]) == pytest.approx(math.sqrt(ss / 3) / 2, abs=1e-12)
        assert float(w[f"{point}_mean"]) == pytest.approx(np.mean(vals), abs=1e-12)
    c = rows[("t1", "calql", "")]
    assert float(c["final_iqm"]) == pytest.approx(0.4, abs=1e-12)
    assert float(c["final_iqm_lo"]) <= 0.4 <= float(c["final_iqm_hi"])
    assert float(c["10k_se"]) == 0.0
    assert float(c["10k_iqm_lo"]) == pytest.approx(0.1, abs=1e-12) == float(c["10k_iqm_hi"])
    assert ("t1", "boto+calql", "0.5") in rows and ("t1", "boto+calql", "-0.5") in rows

    md = (out / "report.md").read_text()
    assert "| t1 | wsrl |  | 4 | 0.30 ± 0.11 | 0.50 ± 0.20 | 0.85 ± 0.06 |" in md
    assert "Skipped" in md and "status is 'running'" in md

    with open(out / "aggregate_iqm.csv", newline="") as f:
        agg = {r["method"]: r for r in csv.DictReader(f)}
    # wsrl over t1 (4 runs) and t2 (2 runs), final: sorted [0, .7, .8, .9, 1, 1], cut 1 each end
    assert float(agg["wsrl"]["final_iqm"]) == pytest.approx((0.7 + 0.8 + 0.9 + 1.0) / 4, abs=1e-12)
    assert "boto+calql" not in agg  # an alpha sweep has no single aggregate
    assert any("boto+calql: no aggregate" in n for n in result.notes)


def test_curves_on_common_grid(runs_dir):
    runs, _ = R.find_runs([runs_dir])
    wsrl = [r for r in runs if r.task == "t1" and r.method == "wsrl"]
    assert wsrl[0].steps.tolist() == [0, 10000, 20000]
    assert wsrl[0].success[0] == pytest.approx(WSRL_INITIAL[0])  # not the earlier 0.99 row
    grid = np.array([0.0, 5000.0, 20000.0, 30000.0])
    curve = R.curve_on_grid(wsrl[0], grid)
    assert curve[1] == pytest.approx((WSRL_INITIAL[0] + WSRL_10K[0]) / 2, abs=1e-12)
    assert np.isnan(curve[3])  # past the run's last evaluation: no made-up value
    curves = np.stack([R.curve_on_grid(r, grid) for r in wsrl])
    mean, se, count = R.mean_se_curves(curves)
    assert mean[0] == pytest.approx(0.3, abs=1e-12) and se[0] == pytest.approx(math.sqrt(0.14 / 3) / 2, abs=1e-12)
    assert count.tolist() == [4, 4, 4, 0] and np.isnan(mean[3])


def test_figures_are_images(runs_dir, tmp_path):
    import matplotlib.image as mpimg

    out = tmp_path / "rep"
    R.make_report([runs_dir], out, n_boot=50)
    for name in ("figure5.png", "alpha_sensitivity.png"):
        img = mpimg.imread(out / name)
        assert img.ndim == 3 and img.shape[0] >= 300 and img.shape[1] >= 500, (name, img.shape)
        assert float(np.std(img[..., :3])) > 0.05, f"{name} looks blank"


def test_select_alpha_and_cli(runs_dir, tmp_path, capsys):
    runs, _ = R.find_runs([runs_dir])
    sel = R.select_alpha(runs)
    (choice,) = sel.choices
    assert choice.task == "t1" and choice.label == "boto+calql"
    assert choice.alpha == 0.0  # ties with 0.5 (0.7 vs 0.7000000000000001): smaller |alpha|
    assert choice.score == pytest.approx(0.7) and choice.n == 2
    assert [a for a, _, _ in choice.ranking] == [0.0, 0.5, -0.5]

    out = tmp_path / "cli"
    assert report_main([str(runs_dir), "--out", str(out), "--select-alpha", "--bootstrap", "100"]) == 0
    printed = capsys.readouterr().out
    assert "t1: alpha = 0  # score 0.700 over 2 seeds, 3 alphas tried" in printed
    assert "skipped" in printed and "status is 'failed'" in printed
    assert (out / "alpha_selection.txt").read_text().startswith("# alpha per task, criterion")


def test_report_bad_dir_is_user_error(tmp_path):
    from botorl.errors import BotorlError

    with pytest.raises(BotorlError, match="not a directory"):
        report_main([str(tmp_path / "nope")])

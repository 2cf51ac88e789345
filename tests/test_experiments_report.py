"""botorl report: exact statistics from run directories written by hand, figures, alpha selection."""

from __future__ import annotations

import csv
import io
import json
import math
import os
from pathlib import Path

import numpy as np
import pytest

from botorl.experiments import dip as D
from botorl.experiments import report as R
from botorl.experiments import runs as RN
from botorl.experiments import stats as S
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
    mean, se, n = S.mean_se(WSRL_INITIAL)
    assert n == 4
    assert mean == pytest.approx(0.3, abs=1e-12)
    assert se == pytest.approx(math.sqrt(0.14 / 3) / 2, abs=1e-12)
    assert math.isnan(S.mean_se([0.5])[1])  # SE of one seed is undefined, not 0
    assert S.iqm(CALQL_FINAL) == pytest.approx(0.4, abs=1e-12)
    assert S.iqm([3.0, 1.0, 2.0, 10.0]) == pytest.approx(2.5, abs=1e-12)  # cut 1 each end
    assert S.iqm([5.0, 1.0, 2.0]) == pytest.approx(8.0 / 3, abs=1e-12)  # n < 4 cuts nothing
    # IQM over tasks pools the runs: 10 scores, cut 2 each end, mean of the middle 6
    t1, t2 = [0.0, 0.1, 0.2, 0.9, 1.0], [0.3, 0.3, 0.5, 0.6, 0.7]
    point, lo, hi = S.stratified_bootstrap_iqm([t1, t2], n_boot=500, seed=1)
    assert point == pytest.approx((0.2 + 0.3 + 0.3 + 0.5 + 0.6 + 0.7) / 6, abs=1e-12)
    assert lo <= point <= hi and hi - lo > 0.05
    # stratified: each task keeps its number of runs, so one run per task never varies
    point, lo, hi = S.stratified_bootstrap_iqm([[0.0], [1.0]], n_boot=300, seed=0)
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
    runs, _ = RN.find_runs([runs_dir])
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
    runs, _ = RN.find_runs([runs_dir])
    sel = R.select_alpha(runs)
    (choice,) = sel.choices
    assert choice.task == "t1" and choice.label == "boto+calql"
    assert choice.alpha == 0.0  # ties with 0.5 (0.7 vs 0.7000000000000001): smaller |alpha|
    # 2 seeds per alpha: seed 0 selects, seed 1 reports
    assert choice.score == pytest.approx(0.7) and choice.n == 1
    assert (choice.select_seeds, choice.report_seeds) == ([0], [1])
    assert [a for a, _, _ in choice.ranking] == [0.0, 0.5, -0.5]

    out = tmp_path / "cli"
    assert report_main([str(runs_dir), "--out", str(out), "--select-alpha", "--bootstrap", "100"]) == 0
    printed = capsys.readouterr().out
    assert ("t1: alpha = 0  # chosen on seeds 0, reported on seeds 1: held-out score 0.700, no CI from 1 seed "
            "(n=1); in-sample 0.700 (n=1); 3 alphas tried") in printed
    assert "skipped" in printed and "status is 'failed'" in printed
    assert (out / "alpha_selection.txt").read_text().startswith("# alpha per task, criterion")


def test_report_bad_dir_is_user_error(tmp_path):
    from botorl.errors import BotorlError

    with pytest.raises(BotorlError, match="not a directory"):
        report_main([str(tmp_path / "nope")])


# ---------------------------------------------------------------------------------------------
# The dip


def _dip_run(root: Path, seed: int, curve: list[tuple[int, float]], *, method: str = "wsrl",
             warmup: list[tuple[int, float]] = (), task: str = "d1") -> Path:
    rows = [f"warmup,{step},{succ},0,0,0" for step, succ in warmup]  # the warm-up's evaluations
    succ = dict(list(warmup) + list(curve))
    return write_run(root, task=task, method=method, seed=seed, initial=succ.get(0, 0.0), s10k=0.0,
                     final=curve[-1][1], curve=curve, extra_rows=rows)


def test_dip_by_hand(tmp_path):
    # 1.0 at 0, 0.4 at 2.5k (a warm-up evaluation), 0.0 at 5k, 1.0 at 12.5k
    d = _dip_run(tmp_path, 0, [(0, 1.0), (5000, 0.0), (12500, 1.0)], warmup=[(2500, 0.4)])
    runs, _ = RN.find_runs([tmp_path])
    (run,) = runs
    dip = D.run_dip(run, 10_000)
    assert dip.value == pytest.approx(-1.0, abs=1e-12)
    assert (dip.initial, dip.lowest, dip.lowest_step, dip.evals, dip.last_step) == (1.0, 0.0, 5000.0, 3, 5000.0)
    # a 3k window sees only step 0 and the warm-up's 2.5k evaluation
    assert D.run_dip(run, 3000).value == pytest.approx(-0.6, abs=1e-12)
    assert D.run_dip(run, 2500).value == pytest.approx(-0.6, abs=1e-12)  # the window's end is inside
    # no fall: the dip is 0, not the rise to 1.0 at 12.5k
    assert D.run_dip(RN.find_runs([_dip_run(tmp_path / "flat", 1, [(0, 0.5), (5000, 0.5), (12500, 1.0)])])[0][0],
                     10_000).value == 0.0

    out = tmp_path / "cli"
    assert report_main([str(d), "--out", str(out), "--dip-window", "3000", "--bootstrap", "50"]) == 0
    with open(out / "dip_runs.csv", newline="") as f:
        (row,) = list(csv.DictReader(f))
    assert float(row["dip"]) == pytest.approx(-0.6, abs=1e-12) and row["lowest_step"] == "2500"
    with open(out / "table1.csv", newline="") as f:
        (row,) = list(csv.DictReader(f))
    assert float(row["dip_mean"]) == pytest.approx(-0.6, abs=1e-12) and row["dip_n"] == "1"
    assert row["dip_lo"] == "" and row["dip_se"] == ""  # one run: no spread, no CI
    assert "## The dip (first 3000 online env steps)" in (out / "report.md").read_text()


def test_runs_without_a_dip_are_listed(tmp_path, capsys):
    _dip_run(tmp_path, 0, [(0, 1.0), (5000, 0.0), (20000, 1.0)])
    late = _dip_run(tmp_path, 1, [(2500, 1.0), (5000, 0.0), (20000, 1.0)])  # no evaluation at step 0
    sparse = _dip_run(tmp_path, 2, [(0, 1.0), (15000, 0.0)])  # none after 0 inside the window
    out = tmp_path / "rep"
    assert report_main([str(tmp_path), "--out", str(out), "--bootstrap", "50"]) == 0
    printed = capsys.readouterr().out
    assert f"no dip for {late}: eval.csv has no evaluation at env_step 0 (the first is at 2500)" in printed
    assert (f"no dip for {sparse}: eval.csv has no evaluation after env_step 0 within the 10000-step dip "
            "window (the next is at 15000)") in printed
    with open(out / "table1.csv", newline="") as f:
        (row,) = list(csv.DictReader(f))
    assert row["initial_n"] == "3" and row["dip_n"] == "1"  # they still count in Table 1
    assert float(row["dip_mean"]) == -1.0
    md = (out / "report.md").read_text()
    # the report's files name runs relative to the report (no path of the machine that made it)
    rel_late = os.path.relpath(late, out)
    assert "Finished runs without a dip:" in md and f"- `{rel_late}`: eval.csv has no evaluation at env_step 0" in md
    assert str(tmp_path) not in md


# five runs of wsrl and three of boto on d1; wsrl's dips by hand
WSRL_DIPS = [-1.0, -0.6, -0.2, 0.0, -0.4]  # mean -0.44; sorted, cut 1 each end: IQM -0.4


@pytest.fixture(scope="module")
def dip_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("dips")
    for seed, dip in enumerate(WSRL_DIPS):
        _dip_run(root, seed, [(0, 1.0), (5000, 1.0 + dip), (10000, 1.0), (20000, 1.0)])
    for seed, dip in enumerate([0.0, -0.1, -0.2]):
        _dip_run(root, seed, [(0, 0.9), (5000, 0.9 + dip), (20000, 1.0)], method="boto")
    _dip_run(root, 0, [(0, 0.5), (2500, 0.0), (20000, 0.0)], task="d2")
    return root


def test_dip_group_statistics(dip_dir, tmp_path):
    result = R.make_report([dip_dir], tmp_path / "a", n_boot=2000, seed=3)
    cell = next(c for c in result.dip_cells if (c.task, c.label) == ("d1", "wsrl"))
    st = cell.stats
    x = np.asarray(WSRL_DIPS)
    assert st["n"] == 5 and st["mean"] == pytest.approx(-0.44, abs=1e-12)
    assert st["se"] == pytest.approx(x.std(ddof=1) / math.sqrt(5), abs=1e-12)
    assert st["iqm"] == pytest.approx(-0.4, abs=1e-12)
    assert st["lo"] < st["mean"] < st["hi"] and st["iqm_lo"] <= st["iqm"] <= st["iqm_hi"]
    # the percentile bootstrap of a mean is close to mean +- 1.96 sd/sqrt(n) (sd with ddof=0);
    # 20% is wide enough for 2000 resamples of 5 values and narrow enough to catch a wrong scale
    assert st["hi"] - st["lo"] == pytest.approx(2 * 1.96 * x.std() / math.sqrt(5), rel=0.2)
    # reproducible for a seed, and the seed matters
    again = R.make_report([dip_dir], tmp_path / "b", n_boot=2000, seed=3)
    assert (tmp_path / "a" / "table1.csv").read_text() == (tmp_path / "b" / "table1.csv").read_text()
    assert next(c for c in again.dip_cells if (c.task, c.label) == ("d1", "wsrl")).stats == st
    assert S.bootstrap_mean_ci(WSRL_DIPS, n_boot=2000, seed=3) == pytest.approx((st["lo"], st["hi"]), abs=1e-12)
    spread = np.linspace(-1.0, 0.0, 7) ** 3  # 7 distinct values: resampled means rarely coincide
    assert S.bootstrap_mean_ci(spread, n_boot=500, seed=3) == S.bootstrap_mean_ci(spread, n_boot=500, seed=3)
    assert S.bootstrap_mean_ci(spread, n_boot=500, seed=3) != S.bootstrap_mean_ci(spread, n_boot=500, seed=4)

    md = (tmp_path / "a" / "report.md").read_text()
    assert "2000 resamples of the runs, seed 3" in md
    assert f"| d1 | wsrl |  | 5 | 1.00 | 0.56 | -0.44 ± {x.std(ddof=1) / math.sqrt(5):.2f} | " in md
    boto = next(c for c in result.dip_cells if (c.task, c.label) == ("d1", "boto"))
    assert boto.stats["mean"] == pytest.approx(-0.1, abs=1e-12) and boto.initial == pytest.approx(0.9)


def test_dip_figure_is_an_image(dip_dir, tmp_path):
    import matplotlib.image as mpimg

    result = R.make_report([dip_dir], tmp_path, n_boot=50)
    assert tmp_path / "dip.png" in result.files
    img = mpimg.imread(tmp_path / "dip.png")
    assert img.ndim == 3 and img.shape[0] >= 300 and img.shape[1] >= 500, img.shape
    assert float(np.std(img[..., :3])) > 0.05, "dip.png looks blank"
    assert "![the dip](dip.png)" in (tmp_path / "report.md").read_text()


def test_bad_dip_window_is_user_error(dip_dir, tmp_path):
    from botorl.errors import BotorlError

    with pytest.raises(BotorlError, match="--dip-window must be a positive"):
        report_main([str(dip_dir), "--out", str(tmp_path / "x"), "--dip-window", "0"])


# ---------------------------------------------------------------------------------------------
# Held-out alpha selection

# score = (success_10k + success_final) / 2, here both equal the score. Seeds 0-1 select, 2-3
# report (the default split of 4 seeds). On seeds 0-1 alpha 0.5 wins; on seeds 2-3, and on all
# four seeds, alpha 0 wins: choosing on all seeds, or on the report seeds, gives alpha 0.
HELD_OUT = {-0.5: [0.3, 0.3, 0.3, 0.3], 0.0: [0.6, 0.6, 1.0, 1.0], 0.5: [0.9, 0.9, 0.0, 0.2]}


@pytest.fixture(scope="module")
def sweep_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("sweep")
    for alpha, scores in HELD_OUT.items():
        for seed, v in enumerate(scores):
            write_run(root, task="t1", method="boto", pretrain="calql", alpha=alpha, seed=seed,
                      initial=0.5, s10k=v, final=v)
    return root


def test_held_out_selection_chooses_on_selection_seeds(sweep_dir):
    runs, _ = RN.find_runs([sweep_dir])
    (c,) = R.select_alpha(runs, n_boot=1000, seed=0).choices
    assert c.alpha == 0.5 and (c.select_seeds, c.report_seeds) == ([0, 1], [2, 3])
    assert c.in_sample == pytest.approx(0.9, abs=1e-12)
    assert c.score == pytest.approx(0.1, abs=1e-12) and c.n == 2  # seeds 2, 3: 0.0 and 0.2
    assert c.se == pytest.approx(0.1, abs=1e-12)
    assert c.lo == pytest.approx(0.0, abs=1e-12) and c.hi == pytest.approx(0.2, abs=1e-12)
    assert [a for a, _, _ in c.ranking] == [0.5, 0.0, -0.5]

    # the other way round: seeds 2-3 choose alpha 0, seeds 0-1 report it
    (c,) = R.select_alpha(runs, select_seeds=[2, 3]).choices
    assert c.alpha == 0.0 and c.report_seeds == [0, 1]
    assert c.score == pytest.approx(0.6, abs=1e-12) and c.in_sample == pytest.approx(1.0, abs=1e-12)
    # an explicit report set smaller than the rest
    (c,) = R.select_alpha(runs, select_seeds=[0, 1], report_seeds=[3]).choices
    assert c.alpha == 0.5 and c.report_seeds == [3] and c.score == pytest.approx(0.2, abs=1e-12)


def test_alpha_table_by_hand(sweep_dir, tmp_path):
    """Per alpha, mean ± s.e. over seeds of the success and of the dip (the runs' curves are
    0 -> 10k -> 20k, so the dip is min(0.5, v) - 0.5)."""
    runs, _ = RN.find_runs([sweep_dir])
    rows = {r.alpha: r for r in R.alpha_table(runs, window=10_000)}
    assert sorted(rows) == [-0.5, 0.0, 0.5] and all(r.n == 4 and r.label == "boto+calql" for r in rows.values())
    # alpha 0.5: v = 0.9, 0.9, 0, 0.2 -> dips 0, 0, -0.5, -0.3: mean -0.2, var (.04+.04+.09+.01)/3 = .06
    m, se = rows[0.5].stats["dip"]
    assert m == pytest.approx(-0.2, abs=1e-12) and se == pytest.approx(math.sqrt(0.06 / 4), abs=1e-12)
    assert rows[0.0].stats["dip"] == (pytest.approx(0.0, abs=1e-12), pytest.approx(0.0, abs=1e-12))
    assert rows[-0.5].stats["dip"][0] == pytest.approx(-0.2, abs=1e-12)
    assert rows[0.0].stats["success_10k"][0] == pytest.approx(0.8, abs=1e-12)
    out = tmp_path / "rep"
    R.make_report([sweep_dir], out, n_boot=50)
    with open(out / "alpha_sensitivity.csv") as f:
        table = {float(r["alpha"]): r for r in csv.DictReader(f)}
    assert float(table[0.5]["dip_mean"]) == pytest.approx(-0.2, abs=1e-6) and table[0.5]["n"] == "4"
    assert "alpha_sensitivity.csv" in (out / "report.md").read_text()


def test_held_out_selection_cli(sweep_dir, tmp_path, capsys):
    out = tmp_path / "rep"
    assert report_main([str(sweep_dir), "--out", str(out), "--select-alpha", "--select-seeds", "2-3",
                        "--bootstrap", "200"]) == 0
    printed = capsys.readouterr().out
    assert "Seeds: 2-3 select (--select-seeds), every other seed reports." in printed
    assert ("t1: alpha = 0  # chosen on seeds 2-3, reported on seeds 0-1: held-out score 0.600 ± 0.000, "
            "95% CI [0.600, 0.600] (n=2); in-sample 1.000 (n=2); 3 alphas tried; next alpha = -0.5") in printed
    text = (out / "alpha_selection.txt").read_text()
    assert "chosen on seeds 2-3, reported on seeds 0-1" in text
    assert "held-out score 0.600" in (out / "report.md").read_text()


def test_held_out_selection_refuses(sweep_dir, tmp_path):
    from botorl.cli import main
    from botorl.errors import BotorlError

    args = [str(sweep_dir), "--out", str(tmp_path / "x"), "--select-alpha", "--bootstrap", "20"]
    with pytest.raises(BotorlError, match="share seeds 2"):
        report_main(args + ["--select-seeds", "0-2", "--report-seeds", "2-3"])
    with pytest.raises(BotorlError, match="none of them in the report set"):
        report_main(args + ["--select-seeds", "0-3"])
    with pytest.raises(BotorlError, match="none of them in the selection set"):
        report_main(args + ["--select-seeds", "7"])
    with pytest.raises(BotorlError, match="--select-seeds 'a-b' is not a seed set"):
        report_main(args + ["--select-seeds", "a-b"])
    assert not (tmp_path / "x").exists()  # refused before writing anything

    # an alpha with one seed: refused by --select-alpha (exit 2), a note in a plain report
    lone = tmp_path / "lone"
    write_run(lone, task="t1", method="boto", alpha=0.0, seed=0, initial=0.5, s10k=1.0, final=1.0)
    for seed in range(2):
        write_run(lone, task="t1", method="boto", alpha=0.5, seed=seed, initial=0.5, s10k=1.0, final=1.0)
    with pytest.raises(BotorlError, match=r"t1 / boto alpha \+0.00 has 1 finished seed\(s\) \(0\); held-out"):
        R.select_alpha(RN.find_runs([lone])[0])
    assert main(["report", str(lone), "--out", str(tmp_path / "y"), "--select-alpha", "--bootstrap", "20"]) == 2
    result = R.make_report([lone], tmp_path / "z", n_boot=20)
    assert result.selection is None and not (tmp_path / "z" / "alpha_selection.txt").exists()
    assert any(n.startswith("no held-out alpha selection: t1 / boto alpha +0.00 has 1") for n in result.notes)


def test_variants_of_a_method_are_not_pooled(tmp_path, capsys):
    """BOTO runs that differ in a setting (the actor trained during BOTO) are two rows, not 4
    seeds of one; runs that differ only in where they log or took their pre-training from are one."""
    def boto(seed, train_actor, **cfg):
        d = write_run(tmp_path, task="t1", method="boto", seed=seed, alpha=-1.0, pretrain="calql",
                      initial=1.0, s10k=1.0, final=1.0 if train_actor else 0.5)
        meta = json.loads((d / "config.json").read_text())
        meta.update(boto={"train_actor": train_actor, "seed": seed, "alpha": -1.0}, out=str(d), **cfg)
        (d / "config.json").write_text(json.dumps(meta))

    boto(0, False)
    boto(1, False, pretrained="/elsewhere", progress=False)
    boto(2, True)
    boto(3, True, checkpoint_every=7)
    runs, _ = RN.find_runs([tmp_path])
    assert sorted({r.label for r in runs}) == ["boto+calql [boto.train_actor=false]",
                                               "boto+calql [boto.train_actor=true]"]
    assert report_main([str(tmp_path), "--out", str(tmp_path / "rep"), "--bootstrap", "20"]) == 0
    with open(tmp_path / "rep" / "table1.csv", newline="") as f:
        rows = {r["method"]: r for r in csv.DictReader(f)}
    assert rows["boto+calql [boto.train_actor=false]"]["seeds"] == "0 1"
    assert float(rows["boto+calql [boto.train_actor=true]"]["final_mean"]) == 1.0


def test_dip_of_a_method_without_pretraining_is_marked(tmp_path):
    # rlpd starts from an untrained policy: a lucky 0.7 at step 0 is not unlearning
    _dip_run(tmp_path, 0, [(0, 0.7), (2500, 0.0), (20000, 1.0)], method="rlpd")
    _dip_run(tmp_path, 0, [(0, 1.0), (2500, 0.0), (20000, 1.0)], method="wsrl")
    result = R.make_report([tmp_path], tmp_path / "rep", n_boot=50)
    by_label = {c.label: c for c in result.dip_cells}
    assert by_label["rlpd"].from_scratch and not by_label["wsrl"].from_scratch
    assert by_label["rlpd"].stats["mean"] == pytest.approx(-0.7, abs=1e-12)  # still computed, only marked
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "rlpd on d1 trains from scratch (no pre-training)" in md
    assert "wsrl on d1 trains from scratch" not in md


def test_alpha_csv_keeps_a_label_with_commas_in_one_field():
    """A variant's label joins its settings with ", " (runs.py): the CSV must quote it, so every
    row keeps as many fields as its header."""
    row = R.AlphaRow(task="pointmaze-medium", label="boto+calql [boto.noise=none, online_reseed=1]", alpha=-1.0, n=8,
                     stats={f: (0.5, 0.1) for f in R.ALPHA_FIELDS})
    (parsed,) = list(csv.DictReader(io.StringIO(R.alpha_csv([row]))))
    assert parsed["method"] == row.label and parsed["alpha"] == "-1" and parsed["dip_se"] == "0.1"

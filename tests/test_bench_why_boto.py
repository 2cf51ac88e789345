"""benchmarks/why_boto.py: the ablation study's analysis. Arms pair within one block's
paired.csv (one machine's pre-trainings), the differences of differences ((b) − (d), the BOTO
floor) come from two rows of one seed, and Holm's correction is checked by hand."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np

from botorl.experiments.pairs import QUANTITIES, Pair, pairs_csv

_spec = importlib.util.spec_from_file_location("why_boto", Path(__file__).resolve().parents[1] / "benchmarks" / "why_boto.py")
WB = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(WB)


def _pair(seed, label, alpha, dip, s10k, ref_dip=-1.0):
    ref = {q: 1.0 for q in QUANTITIES} | {"dip": ref_dip, "lowest": 1.0 + ref_dip, "success_10k": 0.5}
    other = {q: 1.0 for q in QUANTITIES} | {"dip": dip, "lowest": 1.0 + dip, "success_10k": s10k}
    return Pair("pointmaze-medium", seed, label, alpha, "wsrl", ref, other)


B = 'boto+calql [boto.noise="hybrid"]'
D = 'boto+calql [boto.noise="none"]'
F2 = 'boto+calql [boto.noise="hybrid", online_reseed=1]'


def test_arms_pair_within_a_block_and_differences_by_hand(tmp_path):
    b0, b1 = tmp_path / "b0" / "paired.csv", tmp_path / "b1" / "paired.csv"
    b0.parent.mkdir()
    b1.parent.mkdir()
    b0.write_text(pairs_csv([_pair(0, B, -1.0, -0.2, 1.0), _pair(0, D, -1.0, -0.5, 1.0), _pair(0, F2, -1.0, -0.4, 1.0),
                             _pair(1, B, -1.0, -1.0, 0.5), _pair(1, D, -1.0, -0.8, 0.0),
                             _pair(1, "wsrl [online_reseed=1]", None, -0.9, 0.5),
                             _pair(1, B, 0.0, 0.0, 1.0)]))  # alpha 0: an arm the plan does not name
    # block 1's seed 0 is another machine's pre-training: it must not pair with block 0's
    b1.write_text(pairs_csv([_pair(0, D, -1.0, 0.0, 1.0, ref_dip=-0.5)]))
    t = WB.table([b0, b1])
    assert ("b0", "c", 1) not in t and ("b1", "b", 0) not in t
    bd = WB.differences(t, "b", "d", "dip")
    np.testing.assert_allclose(sorted(bd.values), sorted([-0.2 - -0.5, -1.0 - -0.8]))  # +0.3, -0.2
    da = WB.differences(t, "d", "a", "dip")
    np.testing.assert_allclose(sorted(da.values), sorted([-0.5 - -1.0, -0.8 - -1.0, 0.0 - -0.5]))
    assert sorted(da.blocks.tolist()) == ["b0", "b0", "b1"]
    f2 = WB.differences(t, "f2", "b", "dip").values
    np.testing.assert_allclose(f2, [-0.4 - -0.2])
    f1 = WB.differences(t, "f1", "a", "success_10k").values
    np.testing.assert_allclose(f1, [0.0])
    rows = WB.primary_rows(t)
    bd_dip = next(r for r in rows if r["endpoint"] == "dip" and r["comparison"].startswith("(b)") and "(d)" in r["comparison"])
    assert bd_dip["n"] == 2 and math.isclose(bd_dip["mean"], 0.05) and bd_dip["bew"] == (1, 0, 1)
    floors = WB.floor_rows(t)
    assert [r["n"] for r in floors] == [1, 1, 1, 1]


def test_holm_by_hand():
    # m = 5 (the nan test counts in the family): 0.01 x5 = 0.05, 0.02 x4 = 0.08, 0.03 x3 = 0.09,
    # 0.5 x2 = 1.0
    got = WB.holm([0.03, 0.5, 0.01, math.nan, 0.02])
    want = [0.09, 1.0, 0.05, math.nan, 0.08]
    assert WB.holm([0.04, 0.01]) == [0.04, 0.02]  # step-down keeps the order monotone
    for g, w in zip(got, want):
        assert (math.isnan(g) and math.isnan(w)) or math.isclose(g, w)


def test_block_bootstrap_needs_two_blocks_and_spans_the_block_means():
    d = WB.Diffs(np.array([0.0, 0.0, 1.0, 1.0]), np.array(["b0", "b0", "b1", "b1"]))
    lo, hi = WB.block_bootstrap(d, n_boot=2000)
    assert lo == 0.0 and hi == 1.0  # resampling 2 blocks: means 0, 0.5 or 1
    one = WB.Diffs(np.array([0.1, 0.2]), np.array(["b0", "b0"]))
    assert all(math.isnan(x) for x in WB.block_bootstrap(one))

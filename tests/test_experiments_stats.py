"""experiments/stats.py's study statistics against values computed by hand (in the comments),
and the corrected Holm p of study 1 (docs/results/why-boto) from its committed paired.csv."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from botorl.experiments.pairs import read_pairs_csv
from botorl.experiments.stats import (
    ZERO,
    block_range,
    detectable_effect,
    holm,
    tost,
    wilcoxon_signed_rank,
)

ROOT = Path(__file__).resolve().parents[1]


def test_wilcoxon_exact_by_counting_subsets():
    # n = 5, all positive: W+ = 15, only the full set of {1..5} reaches it: P(W+ >= 15) = 1/32,
    # two-sided p = 2/32
    assert wilcoxon_signed_rank([0.1, 0.2, 0.3, 0.4, 0.5]) == (pytest.approx(2 / 32), "exact")
    assert type(wilcoxon_signed_rank([0.1, 0.2])[0]) is float  # not numpy's: it is written to reports
    # d = 1, -2, 3, 4: W+ = 1 + 3 + 4 = 8; subsets of {1,2,3,4} summing to >= 8: {4,3,1}, {4,3,2},
    # {4,3,2,1} -> 3/16, P(W+ <= 8) = 14/16, p = 2 * 3/16
    assert wilcoxon_signed_rank([1.0, -2.0, 3.0, 4.0]) == (pytest.approx(6 / 16), "exact")
    # symmetric in sign
    assert wilcoxon_signed_rank([-1.0, 2.0, -3.0, -4.0]) == (pytest.approx(6 / 16), "exact")


def test_wilcoxon_drops_zeros_and_nan():
    # two zeros and a nan dropped: n = 2, W+ = 3 = the largest sum: P = 1/4, p = 1/2
    assert wilcoxon_signed_rank([0.0, ZERO / 2, math.nan, 1.0, 2.0]) == (pytest.approx(0.5), "exact")
    p, method = wilcoxon_signed_rank([0.0, -0.0, ZERO])
    assert math.isnan(p) and method == "none"
    p, method = wilcoxon_signed_rank([])
    assert math.isnan(p) and method == "none"


def test_wilcoxon_normal_with_tie_correction_no_continuity_correction():
    # d = 1, 1, -2, 3: |d| ranks 1.5, 1.5, 3, 4; W+ = 1.5 + 1.5 + 4 = 7; n = 4: mean 4*5/4 = 5,
    # var = 4*5*9/24 - (2^3 - 2)/48 = 7.5 - 0.125 = 7.375; z = 2 / sqrt(7.375);
    # p = 2 (1 - Phi(z)) = erfc(z / sqrt 2)
    z = 2 / math.sqrt(7.375)
    assert wilcoxon_signed_rank([1.0, 1.0, -2.0, 3.0]) == (pytest.approx(math.erfc(z / math.sqrt(2))), "normal")
    # differences of success rates: 0.7 - 0.4 is 0.29999999999999993, tied with 0.3 all the same
    # (else this would be an exact test of 3 distinct values)
    assert 0.7 - 0.4 != 0.3
    # |d| 0.3, 0.3, 0.5: ranks 1.5, 1.5, 3; W+ = 1.5 + 3 = 4.5; mean 3, var 3*4*7/24 - 6/48 = 3.375
    z = 1.5 / math.sqrt(3.375)
    assert wilcoxon_signed_rank([0.7 - 0.4, -0.3, 0.5]) == (pytest.approx(math.erfc(z / math.sqrt(2))), "normal")


def test_wilcoxon_more_than_50_distinct_is_normal():
    # d = 1..51, all positive, no ties: W+ = 51*52/2 = 1326, mean 663, var 51*52*103/24 = 11381.5
    z = 663 / math.sqrt(11381.5)
    p, method = wilcoxon_signed_rank([float(k) for k in range(1, 52)])
    assert method == "normal" and p == pytest.approx(math.erfc(z / math.sqrt(2)))
    # n = 50 is still exact: P(W+ = 1275) = 2^-50
    assert wilcoxon_signed_rank([float(k) for k in range(1, 51)]) == (pytest.approx(2 * 2.0**-50), "exact")


def test_holm_by_hand():
    # m = 4: sorted 0.005 x4 = 0.02, 0.01 x3 = 0.03, 0.03 x2 = 0.06, 0.04 x1 = 0.04 -> max(0.06, 0.04)
    assert holm([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    # a nan test counts in m = 5: 0.01 x5 = 0.05, 0.02 x4 = 0.08, 0.03 x3 = 0.09, 0.5 x2 = 1.0 (capped)
    got = holm([0.03, 0.5, 0.01, math.nan, 0.02])
    assert math.isnan(got[3]) and [got[i] for i in (0, 1, 2, 4)] == pytest.approx([0.09, 1.0, 0.05, 0.08])


def test_block_range_is_the_block_means():
    # b0: (3 + 10) / 2 = 6.5, b1: (1 + 2) / 2 = 1.5; nan ignored
    lo, hi, means = block_range([1.0, 2.0, 3.0, 10.0, math.nan], ["b1", "b1", "b0", "b0", "b0"])
    assert (lo, hi) == (1.5, 6.5) and means == [("b0", 6.5), ("b1", 1.5)]
    lo, hi, means = block_range([], [])
    assert math.isnan(lo) and math.isnan(hi) and means == []


def test_tost_verdicts():
    # d = -0.02, 0, 0.02: mean 0, SD 0.02, SE 0.02 / sqrt 3; t_{0.95, 2} = 2.919986:
    # 90% CI = +-0.033717, inside +-0.1 -> equivalent. With 2 degrees of freedom the t tail is
    # 0.5 (1 - t / sqrt(t^2 + 2)); t = 0.1 / SE = sqrt(75): p = 0.5 (1 - sqrt(75 / 77))
    r = tost([-0.02, 0.0, 0.02], 0.1)
    assert r["verdict"] == "equivalent" and r["margin"] == 0.1
    assert r["ci90"] == pytest.approx((-0.033717, 0.033717), abs=1e-6)
    assert r["p"] == pytest.approx(0.5 * (1 - math.sqrt(75 / 77)))
    # d = 0.8, 1, 1.2: SE 0.2 / sqrt 3; 95% = 1 +- 4.302653 * 0.11547 = [0.503, 1.497] excludes 0
    assert tost([0.8, 1.0, 1.2], 0.1)["verdict"] == "different"
    # d = -1, 0, 1: neither; SE 1 / sqrt 3, t = 0.1 sqrt 3, t^2 = 0.03: p = 0.5 (1 - t / sqrt 2.03)
    r = tost([-1.0, 0.0, 1.0], 0.1)
    assert r["verdict"] == "undecided" and r["p"] == pytest.approx(0.5 * (1 - 0.1 * math.sqrt(3) / math.sqrt(2.03)))
    # narrower margin than the 90% CI: undecided, though the 95% CI includes 0
    assert tost([-0.02, 0.0, 0.02], 0.03)["verdict"] == "undecided"
    r = tost([0.5], 0.1)
    assert r["verdict"] == "undecided" and math.isnan(r["p"])


def test_detectable_effect():
    # (1.959964 + 0.841621) * 0.46 / sqrt(24) = 2.801585 * 0.093897 = 0.26306
    assert detectable_effect(0.46, 24) == pytest.approx(0.26306, abs=1e-4)
    assert math.isnan(detectable_effect(0.46, 1))


def test_study_1_holm_p_with_the_plans_wilcoxon():
    """docs/results/why-boto: the 10 primary tests (5 comparisons x dip, success at 10k), pooled
    over blocks b0-b2 with arms paired within a block's paired.csv; the plan's Wilcoxon (ties:
    normal, no continuity correction) gives Holm p 0.041 for (b) − (a) and (d) − (a), 0.030
    for (c) − (a) on the dip (SciPy 1.17's default exact permutation p gave 0.018 and 0.010)."""
    arms = {('boto+calql [boto.backup_entropy=true, boto.noise="hybrid"]', -1.0): "b",
            ('boto+calql [boto.backup_entropy=true, boto.noise="hybrid"]', 1.0): "c",
            ('boto+calql [boto.backup_entropy=true, boto.noise="none"]', -1.0): "d",
            ('boto+calql [boto.backup_entropy=false, boto.noise="hybrid"]', -1.0): "e"}
    diff: dict[tuple[str, str, int], dict[str, float]] = {}  # (block, arm, seed) -> arm − WSRL
    for block in ("b0", "b1", "b2"):
        for p in read_pairs_csv(ROOT / "docs" / "results" / "why-boto" / block / "paired.csv"):
            if (p.label, p.alpha) in arms:
                diff[(block, arms[(p.label, p.alpha)], p.seed)] = {q: p.diff(q) for q in ("dip", "success_10k")}

    def d(x: str, y: str | None, q: str) -> list[float]:
        return [v[q] - (diff[(b, y, s)][q] if y else 0.0) for (b, a, s), v in sorted(diff.items()) if a == x]

    tests = [(x, y, q) for q in ("dip", "success_10k") for x, y in (("b", None), ("c", None), ("d", None),
                                                                    ("e", None), ("b", "d"))]
    ps = [wilcoxon_signed_rank(d(x, y, q)) for x, y, q in tests]
    assert all(len(d(x, y, q)) == 24 for x, y, q in tests) and {m for _, m in ps} == {"normal"}
    adjusted = [round(p, 3) for p in holm([p for p, _ in ps])]
    assert adjusted[:3] == [0.041, 0.030, 0.041]


def test_wilcoxon_agrees_with_scipy_where_scipy_is_told_the_method():
    # an independent implementation as a cross-check: SciPy's explicit methods (not its
    # version-dependent default) on tied and on untied samples
    from scipy import stats

    rng = np.random.default_rng(0)
    for n in (6, 13, 30):
        tied = rng.integers(-3, 5, n).astype(float) / 4  # steps of 0.25, as success rates tie
        tied = tied[tied != 0]
        p, method = wilcoxon_signed_rank(tied)
        assert method == "normal"
        assert p == pytest.approx(stats.wilcoxon(tied, method="approx", correction=False).pvalue, rel=1e-9)
        untied = rng.normal(0.3, 1.0, n)
        p, method = wilcoxon_signed_rank(untied)
        assert method == "exact"
        assert p == pytest.approx(stats.wilcoxon(untied, method="exact").pvalue, rel=1e-9)

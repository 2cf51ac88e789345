"""benchmarks/paired_alphas.py: BOTO at one alpha against another pairs only within one
pre-training (one paired.csv file), and its table is the report's statistics of those pairs."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from botorl.experiments.pairs import QUANTITIES, Pair, pairs_csv, paired_table

_spec = importlib.util.spec_from_file_location(
    "paired_alphas", Path(__file__).resolve().parents[1] / "benchmarks" / "paired_alphas.py")
PA = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(PA)


def _pair(seed, alpha, dip, label="boto+calql"):
    ref = {q: 1.0 for q in QUANTITIES} | {"dip": -1.0, "lowest": 0.0}
    other = {q: 1.0 for q in QUANTITIES} | {"dip": dip, "lowest": 1.0 + dip}
    return Pair("pointmaze-medium", seed, label, alpha, "wsrl", ref, other)


def test_alphas_pair_within_a_file_never_across(tmp_path):
    a = tmp_path / "a.csv"
    b = tmp_path / "b.csv"
    # file a: seed 0 at both alphas; seed 1 only at -1 (no pair); file b: seed 0 only at +1,
    # which must not pair with file a's seed 0 (another machine's pre-training).
    a.write_text(pairs_csv([_pair(0, -1.0, -0.9), _pair(0, 1.0, -0.2), _pair(1, -1.0, -0.5),
                            _pair(0, None, -0.8, label="wsrl [online_reseed=1]")]))
    b.write_text(pairs_csv([_pair(0, 1.0, 0.0), _pair(2, -1.0, -1.0), _pair(2, 1.0, -0.4)]))
    pairs = PA.alpha_pairs([a, b])
    assert sorted((p.seed, p.label, p.reference) for p in pairs) == [(0, "alpha+1", "alpha-1"), (2, "alpha+1", "alpha-1")]
    (dip,) = [c for c in paired_table(pairs, n_boot=200) if c.quantity == "dip"]
    # by hand: seed 0: -0.2 - (-0.9) = 0.7; seed 2: -0.4 - (-1.0) = 0.6
    assert dip.n == 2 and abs(dip.mean - 0.65) < 1e-9 and (dip.better, dip.equal, dip.worse) == (2, 0, 0)
    assert not dip.noise_floor


def test_hold_counts_by_hand(tmp_path):
    a = tmp_path / "a.csv"
    # seed 0: both alphas hold (lowest 0.8, 0.6); seed 1: one holds (0.9), one falls (0.0);
    # seed 2: only one alpha ran, not counted. Hold rate 3/4 -> independent 2 * (1/16, 6/16, 9/16).
    a.write_text(pairs_csv([_pair(0, -1.0, -0.2), _pair(0, 1.0, -0.4), _pair(1, -1.0, -0.1), _pair(1, 1.0, -1.0),
                            _pair(2, 1.0, -1.0)]))
    observed, independent = PA.hold_counts([a])
    assert observed == {0: 0, 1: 1, 2: 1}
    assert [round(independent[k], 6) for k in range(3)] == [0.125, 0.75, 1.125]

"""benchmarks/paired_sizes.py: two studies' pairs keep apart (a seed's quick and mid runs start
from different pre-trainings), each with the report's statistics of its own pairs."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from botorl.experiments.pairs import QUANTITIES, Pair, pairs_csv, paired_table

_spec = importlib.util.spec_from_file_location(
    "paired_sizes", Path(__file__).resolve().parents[1] / "benchmarks" / "paired_sizes.py")
PS = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(PS)


def _pair(seed, dip):
    ref = {q: 1.0 for q in QUANTITIES} | {"dip": -1.0}
    other = {q: 1.0 for q in QUANTITIES} | {"dip": dip}
    return Pair("pointmaze-medium", seed, "boto+calql", -1.0, "wsrl", ref, other)


def test_studies_never_pool(tmp_path):
    quick, mid = tmp_path / "quick.csv", tmp_path / "mid.csv"
    quick.write_text(pairs_csv([_pair(0, -0.5), _pair(1, -1.0)]))
    mid.write_text(pairs_csv([_pair(0, 0.0), _pair(1, 0.0), _pair(2, -1.0)]))
    pairs = PS.sized_pairs([f"quick={quick}", f"mid={mid}"])
    cells = {c.task: c for c in paired_table(pairs, n_boot=200) if c.quantity == "dip"}
    assert set(cells) == {"pointmaze-medium (quick)", "pointmaze-medium (mid)"}
    # by hand: quick +0.5 and 0 -> +0.25 over 2 pairs; mid +1, +1, 0 -> +2/3 over 3 pairs
    assert cells["pointmaze-medium (quick)"].n == 2 and abs(cells["pointmaze-medium (quick)"].mean - 0.25) < 1e-9
    assert cells["pointmaze-medium (mid)"].n == 3 and abs(cells["pointmaze-medium (mid)"].mean - 2 / 3) < 1e-9
    assert (cells["pointmaze-medium (mid)"].better, cells["pointmaze-medium (mid)"].equal) == (2, 1)


def test_a_study_without_a_name_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="NAME=PATH"):
        PS.sized_pairs([str(tmp_path / "paired.csv")])

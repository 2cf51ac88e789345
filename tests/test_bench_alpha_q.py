"""python benchmarks/alpha_q.py end to end on the smoke profile: one pre-training run,
the chosen arms measured at each step, a second call resumes (keeps the measured arms)."""

from __future__ import annotations

import csv
import importlib.util
from pathlib import Path

import pytest

from botorl.errors import ConfigError

_spec = importlib.util.spec_from_file_location("alpha_q", Path(__file__).resolve().parents[1] / "benchmarks" / "alpha_q.py")
AQ = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(AQ)


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.slow  # ~70 s: a benchmark's whole run, resumed
def test_alpha_q_measures_the_chosen_arms_and_resumes(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    args = ["--task", "pointmaze-umaze", "--profile", "smoke", "--seeds", "0-0", "--steps", "5,10", "--states", "20",
            "--out", str(tmp_path / "aq")]
    assert AQ.main(args + ["--arms", "alpha=-1"]) == 0
    first = _rows(tmp_path / "aq" / "alpha_q.csv")
    assert [(r["arm"], r["step"]) for r in first] == [("pre-trained", "0"), ("alpha=-1", "5"), ("alpha=-1", "10")]
    # an arm whose name holds ", " is chosen whole; the measured arm is kept, not run again
    assert AQ.main(args + ["--arms", "alpha=-1,alpha=-1, no entropy term"]) == 0
    rows = _rows(tmp_path / "aq" / "alpha_q.csv")
    assert rows[:3] == first
    assert [(r["arm"], r["step"]) for r in rows[3:]] == [("alpha=-1, no entropy term", "5"),
                                                         ("alpha=-1, no entropy term", "10")]
    assert (tmp_path / "aq" / "alpha_q.png").exists() and (tmp_path / "aq" / "alpha_q_scale.csv").exists()
    # Theorem 2's ordering needs Q off the data: every distance is measured
    assert all(r[f"q_d{d:g}"] for r in rows for d in AQ.DISTANCES)
    with pytest.raises(ConfigError, match="unknown arm"):
        AQ.main(args + ["--arms", "alpha=2"])

"""botorl report's paired comparison: pairs found by pre-training fingerprint, statistics by hand."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from botorl.configs.presets import make_preset
from botorl.configs.resolve import resolve
from botorl.configs.schema import to_dict
from botorl.experiments import pairs as PR
from botorl.experiments import report as R
from botorl.experiments import runs as RN

# Hand-made numbers, 4 seeds from one pre-training each. Every run starts at 0.8.
WSRL_LOWEST = [0.2, 0.4, 0.8, 0.6]  # dips -0.6, -0.4, 0, -0.2
WSRL_10K = [0.5, 0.5, 0.9, 0.6]
BOTO_LOWEST = [0.6, 0.4, 0.8, 0.7]  # dips -0.2, -0.4, 0, -0.1 -> differences +0.4, 0, 0, +0.1
BOTO_10K = [0.7, 0.6, 0.9, 0.8]  # differences +0.2, +0.1, 0, +0.2


def _config(method: str, seed: int, alpha: float | None = None, reseed: int = 0) -> dict:
    d = to_dict(resolve(make_preset("pointmaze-umaze", "smoke", method)))
    d.update(seed=seed, alpha=alpha, online_reseed=reseed)
    d["warmup"]["steps"] = 5000
    d["eval"]["dense_interval"] = 500
    return d


def _write(root: Path, name: str, config: dict, lowest: float, s10k: float, early: float) -> Path:
    d = root / name
    d.mkdir(parents=True)
    (d / "config.json").write_text(json.dumps(config))
    summary = {k: config[k] for k in ("task", "method", "seed", "alpha", "pretrain", "profile")}
    summary.update(success_initial=0.8, success_10k=s10k, success_final=1.0, status="finished")
    (d / "summary.json").write_text(json.dumps(summary))
    # an evaluation at 2,500 (before the warm-up's end) that the dense dip must not read, then
    # the dense points 5k..10k with the lowest value at 7k
    curve = [(0, 0.8), (2500, early)] + [(s, lowest if s == 7000 else (s10k if s == 10000 else 0.8))
                                        for s in range(5000, 10001, 500)] + [(20000, 1.0)]
    with open(d / "eval.csv", "w") as f:
        f.write("stage,env_step,success,return\n")
        for s, v in curve:
            f.write(f"finetune,{s},{v},0\n")
    return d


@pytest.fixture(scope="module")
def paired_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("paired")
    for s in range(4):
        _write(root, f"wsrl/seed{s}", _config("wsrl", s), WSRL_LOWEST[s], WSRL_10K[s], early=0.0)
        _write(root, f"boto/seed{s}", _config("boto", s, alpha=0.0), BOTO_LOWEST[s], BOTO_10K[s], early=0.8)
        # the noise floor: WSRL from the same pre-training, another online seed, the same numbers
        _write(root, f"floor/seed{s}", _config("wsrl", s, reseed=1), WSRL_LOWEST[s], WSRL_10K[s], early=0.0)
    # no WSRL run shares these pre-trainings: never paired
    _write(root, "boto/seed9", _config("boto", 9, alpha=0.0), 0.0, 0.0, early=0.8)
    other = _config("boto", 0, alpha=0.5)
    other["offline"]["steps"] += 1  # another pre-training than WSRL seed 0's
    _write(root, "boto-other/seed0", other, 0.0, 0.0, early=0.8)
    return root


def test_pairs_are_runs_of_one_pretraining_and_the_statistics_match_a_hand_computation(paired_dir, tmp_path):
    runs, skipped = RN.find_runs([paired_dir])
    assert not skipped and len(runs) == 14
    pairs, notes = PR.find_pairs(runs)
    assert not notes
    boto = [p for p in pairs if p.label.startswith("boto")]
    floor = [p for p in pairs if p.noise_floor]
    assert len(boto) == 4 and len(floor) == 4 and len(pairs) == 8  # seed 9 and the other pre-training: none
    assert {p.alpha for p in boto} == {0.0} and sorted(p.seed for p in boto) == [0, 1, 2, 3]
    # the dense dip ignores the reference's 0.0 at step 2,500
    by_seed = {p.seed: p for p in boto}
    for s in range(4):
        assert by_seed[s].ref["dip"] == pytest.approx(WSRL_LOWEST[s] - 0.8)
        assert by_seed[s].diff("dip") == pytest.approx(BOTO_LOWEST[s] - WSRL_LOWEST[s])

    cells = {(c.label.split(" ")[0], c.quantity): c for c in PR.paired_table(pairs, n_boot=4000, seed=1)}
    dip = cells[("boto+calql", "dip")]
    d = np.array([0.4, 0.0, 0.0, 0.1])
    assert dip.n == 4 and dip.mean == pytest.approx(0.125)
    assert (dip.better, dip.equal, dip.worse) == (2, 2, 0)
    # t-interval by hand: s.d. = sqrt(0.1075 / 3), t_{0.975, 3} = 3.182446
    half = 3.182446 * math.sqrt(0.1075 / 3) / 2
    assert dip.t_lo == pytest.approx(0.125 - half, abs=1e-5) and dip.t_hi == pytest.approx(0.125 + half, abs=1e-5)
    # Wilcoxon: the zeros dropped, 2 positive differences: exact two-sided p = 2 * 1/4
    assert dip.wilcoxon_p == pytest.approx(0.5) and dip.wilcoxon_method == "exact"
    # the bootstrap CI lies inside the range of the differences and brackets the mean
    assert d.min() <= dip.boot_lo <= 0.125 <= dip.boot_hi <= d.max()
    ten = cells[("boto+calql", "success_10k")]
    assert ten.mean == pytest.approx(0.125) and (ten.better, ten.equal, ten.worse) == (3, 1, 0)
    # the noise floor: identical numbers, zero differences, no p-value
    fl = cells[("wsrl", "dip")]
    assert fl.noise_floor and fl.mean == 0 and fl.equal == 4 and math.isnan(fl.wilcoxon_p)


def test_report_writes_paired_csv_and_table_with_relative_paths(paired_dir, tmp_path):
    out = tmp_path / "report"
    res = R.make_report([paired_dir], out, n_boot=200)
    assert (out / "paired.csv").exists() and (out / "paired_differences.png").exists()
    with open(out / "paired.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 8 == len(res.pairs)
    # (the BOTO runs' labels carry offline.steps: one of them pre-trained differently)
    row = next(r for r in rows if r["method"].startswith("boto+calql") and r["seed"] == "0")
    assert float(row["dip_diff"]) == pytest.approx(0.4) and float(row["dip_reference"]) == pytest.approx(-0.6)
    # read back, the pairs give the same statistics (studies combine several reports' pairs)
    again = PR.paired_table(PR.read_pairs_csv(out / "paired.csv"), n_boot=200)
    assert [(c.label, c.quantity, round(c.mean, 9), c.better) for c in again] == \
        [(c.label, c.quantity, round(c.mean, 9), c.better) for c in res.paired]
    text = (out / "report.md").read_text()
    assert "Paired comparison" in text and "(noise floor)" in text
    for name in ("paired.csv", "dip_runs.csv", "report.md"):
        assert str(paired_dir) not in (out / name).read_text(), f"{name} holds an absolute path"
    assert (out / row["path"]).resolve() == (paired_dir / "boto/seed0").resolve()


def test_pairs_of_earlier_reports_combine_without_their_runs(paired_dir, tmp_path):
    # a study reported block by block: the blocks' paired.csv alone give the study's statistics
    from botorl.experiments.cli import report_main

    first = tmp_path / "block"
    assert report_main([str(paired_dir), "--out", str(first), "--bootstrap", "200"]) == 0
    combined = tmp_path / "study"
    assert report_main(["--pairs-from", str(first / "paired.csv"), "--out", str(combined), "--bootstrap", "200"]) == 0
    assert (combined / "paired_table.csv").read_text() == (first / "paired_table.csv").read_text()
    assert "8 pairs from" in (combined / "report.md").read_text()
    with pytest.raises(Exception, match="paired.csv"):
        report_main(["--pairs-from", str(first / "table1.csv"), "--out", str(tmp_path / "bad")])


def test_blocks_pool_whether_or_not_their_report_held_a_noise_floor(tmp_path):
    """A block reported with its noise floor labels its WSRL "wsrl [online_reseed=0]", a block
    without one plain "wsrl": pooled from their paired.csv, they are one group."""
    from botorl.experiments.pairs import Pair, canonical_label, paired_table, pairs_csv, read_pairs_csv

    assert canonical_label("wsrl [online_reseed=0]") == "wsrl"
    assert canonical_label("wsrl [online_reseed=1]") == "wsrl [online_reseed=1]"
    assert canonical_label("boto+calql [online_reseed=0, online.steps=500]") == "boto+calql [online.steps=500]"
    q = {"success_0": 1.0, "lowest": 0.0, "dip": -1.0, "success_10k": 1.0, "success_final": 1.0}
    blocks = []
    for i, (ref, other) in enumerate([("wsrl [online_reseed=0]", "boto+calql [online_reseed=0]"), ("wsrl", "boto+calql")]):
        path = tmp_path / f"b{i}.csv"
        path.write_text(pairs_csv([Pair("t", i, other, -1.0, ref, q, {**q, "dip": 0.0})]))
        blocks += read_pairs_csv(path)
    cells = paired_table(blocks, quantities=("dip",), n_boot=50)
    assert [(c.label, c.reference, c.n, c.mean) for c in cells] == [("boto+calql", "wsrl", 2, 1.0)]


def test_pairs_match_on_the_pretraining_digest_and_a_mixed_environment_is_named(tmp_path):
    # Same pre-training settings (fingerprint), but seed 1's BOTO run starts from another
    # pre-trained agent (another machine's): it is not paired, and a note says why. Seed 0's
    # runs share the digest and pair. The runs were made in two environments: the report says so.
    sha = {"x": "a" * 64, "y": "b" * 64}
    env = {"commit": "c0", "versions": {"jax": "0.4"}, "cpu": {"model": "M1", "flags": "avx"}, "backend": "cpu"}
    for name, cfg, digest, e in (("wsrl/seed0", _config("wsrl", 0), sha["x"], env),
                                 ("boto/seed0", _config("boto", 0, alpha=0.0), sha["x"], env),
                                 ("wsrl/seed1", _config("wsrl", 1), sha["x"], env),
                                 ("boto/seed1", _config("boto", 1, alpha=0.0), sha["y"],
                                  {**env, "cpu": {"model": "M2", "flags": "avx512"}})):
        d = _write(tmp_path / "runs", name, {**cfg, "environment": e}, 0.4, 0.5, early=0.8)
        summary = json.loads((d / "summary.json").read_text())
        (d / "summary.json").write_text(json.dumps({**summary, "pretrain_sha256": digest}))
    runs, skipped = RN.find_runs([tmp_path / "runs"])
    assert not skipped and len(runs) == 4
    assert all(r.label in ("wsrl", "boto+calql") for r in runs)  # the environment is no setting
    pairs, notes = PR.find_pairs(runs)
    assert [(p.seed, p.label) for p in pairs] == [(0, "boto+calql")]
    assert len(notes) == 1 and "2 different pre-trained agents" in notes[0] and "seed 1" in notes[0]
    env_notes = R.environment_notes(runs, str)
    assert len(env_notes) == 1 and "2 environments" in env_notes[0] and "cpu.flags" in env_notes[0]
    assert R.environment_notes(runs[:1], str) == []

"""BOTO at one alpha against BOTO at another, on the same pre-trainings: does alpha matter?

    python benchmarks/paired_alphas.py docs/results/pointmaze-medium-paired/{b0,b*-rerun}/paired.csv

Reads the ``paired.csv`` files ``botorl report`` wrote (each row BOTO at one alpha against
WSRL from one pre-training) and pairs the BOTO runs of each pre-training with each other: a
row of a file is one seed's pre-training, so alphas pair within a file, never across files
(two files' seed 8 may be two machines' pre-trainings). Prints the report's paired table
(mean difference, bootstrap CI, t-interval, better / equal / worse, Wilcoxon p) for every
pair of alphas, with the same statistics ``botorl report`` uses; then, over the
pre-trainings that succeed at step 0 and ran every alpha, in how many BOTO holds the policy
(lowest success in the window >= ``--hold``) at 0, 1, ... of the alphas, beside the counts that
independent arms with the same hold rate would give (binomial).
"""

from __future__ import annotations

import argparse
import itertools
import math
from pathlib import Path

from botorl.experiments.pairs import Pair, paired_markdown, paired_table, read_pairs_csv


def boto_runs(paths: list[Path]) -> dict[tuple, dict[float, Pair]]:
    """BOTO's pairs by pre-training ``(file, task, seed, label)``, then by alpha."""
    runs: dict[tuple, dict[float, Pair]] = {}
    for path in paths:
        for p in read_pairs_csv(path):
            if p.alpha is not None and not p.noise_floor:
                runs.setdefault((str(path), p.task, p.seed, p.label), {})[p.alpha] = p
    return runs


def alpha_pairs(paths: list[Path]) -> list[Pair]:
    pairs = []
    for (_, task, seed, label), by_alpha in boto_runs(paths).items():
        for low, high in itertools.combinations(sorted(by_alpha), 2):
            pairs.append(Pair(task, seed, f"alpha{high:+g}", high, f"alpha{low:+g}",
                              by_alpha[low].other, by_alpha[high].other,
                              by_alpha[low].other_path, by_alpha[high].other_path))
    return pairs


def hold_counts(paths: list[Path], hold: float = 0.5) -> tuple[dict[int, int], dict[int, float]]:
    """``(observed, independent)``: pre-trainings by how many alphas hold, and the binomial
    expectation at the pooled hold rate. Counts only pre-trainings that ran the most alphas
    any pre-training ran and whose policy succeeds at step 0 (>= ``hold``)."""
    runs = boto_runs(paths).values()
    arms = max((len(r) for r in runs), default=0)
    held = [sum(p.other["lowest"] >= hold for p in r.values()) for r in runs
            if len(r) == arms and next(iter(r.values())).other["success_0"] >= hold]
    observed = {k: held.count(k) for k in range(arms + 1)}
    rate = sum(held) / (arms * len(held)) if held else math.nan
    independent = {k: len(held) * math.comb(arms, k) * rate ** k * (1 - rate) ** (arms - k) for k in range(arms + 1)}
    return observed, independent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("paired_csv", nargs="+", type=Path, help="paired.csv files written by botorl report")
    parser.add_argument("--bootstrap", type=int, default=2000)
    parser.add_argument("--confidence", type=float, default=0.95)
    parser.add_argument("--hold", type=float, default=0.5, help="success that counts as holding the policy")
    args = parser.parse_args()
    pairs = alpha_pairs(args.paired_csv)
    if not pairs:
        raise SystemExit("no pre-training holds BOTO at two alphas in these files; give the paired.csv of "
                         "blocks that ran several alphas.")
    cells = paired_table(pairs, n_boot=args.bootstrap, confidence=args.confidence)
    print(paired_markdown(cells, args.confidence, quantities=("dip", "success_10k")))
    observed, independent = hold_counts(args.paired_csv, args.hold)
    print(f"\npre-trainings by the number of alphas that hold the policy (lowest >= {args.hold:g}), "
          f"{sum(observed.values())} in all:")
    for k in observed:
        print(f"  {k} alphas hold: {observed[k]} (independent arms: {independent[k]:.1f})")


if __name__ == "__main__":
    main()

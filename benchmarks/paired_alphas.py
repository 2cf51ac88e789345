"""BOTO at one alpha against BOTO at another, on the same pre-trainings: does alpha matter?

    python benchmarks/paired_alphas.py docs/results/pointmaze-medium-paired/{b0,b*-rerun}/paired.csv

Reads the ``paired.csv`` files ``botorl report`` wrote (each row BOTO at one alpha against
WSRL from one pre-training) and pairs the BOTO runs of each pre-training with each other: a
row of a file is one seed's pre-training, so alphas pair within a file, never across files
(two files' seed 8 may be two machines' pre-trainings). Prints the report's paired table
(mean difference, bootstrap CI, t-interval, better / equal / worse, Wilcoxon p) for every
pair of alphas, with the same statistics ``botorl report`` uses.
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

from botorl.experiments.pairs import Pair, paired_markdown, paired_table, read_pairs_csv


def alpha_pairs(paths: list[Path]) -> list[Pair]:
    runs: dict[tuple, dict[float, Pair]] = {}
    for path in paths:
        for p in read_pairs_csv(path):
            if p.alpha is not None and not p.noise_floor:
                runs.setdefault((str(path), p.task, p.seed, p.label), {})[p.alpha] = p
    pairs = []
    for (_, task, seed, label), by_alpha in runs.items():
        for low, high in itertools.combinations(sorted(by_alpha), 2):
            pairs.append(Pair(task, seed, f"alpha{high:+g}", high, f"alpha{low:+g}",
                              by_alpha[low].other, by_alpha[high].other,
                              by_alpha[low].other_path, by_alpha[high].other_path))
    return pairs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("paired_csv", nargs="+", type=Path, help="paired.csv files written by botorl report")
    parser.add_argument("--bootstrap", type=int, default=2000)
    parser.add_argument("--confidence", type=float, default=0.95)
    args = parser.parse_args()
    pairs = alpha_pairs(args.paired_csv)
    if not pairs:
        raise SystemExit("no pre-training holds BOTO at two alphas in these files; give the paired.csv of "
                         "blocks that ran several alphas.")
    cells = paired_table(pairs, n_boot=args.bootstrap, confidence=args.confidence)
    print(paired_markdown(cells, args.confidence, quantities=("dip", "success_10k")))


if __name__ == "__main__":
    main()

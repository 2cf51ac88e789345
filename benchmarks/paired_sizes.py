"""BOTO against WSRL at several sizes (profiles): each study's paired differences in one table and one figure.

    python benchmarks/paired_sizes.py quick=docs/results/pointmaze-medium-paired/all-arms/paired.csv \
        mid=docs/results/pointmaze-medium-mid/b0/paired.csv --out docs/results/paired-sizes.png

Each ``NAME=PATH`` is the ``paired.csv`` a ``botorl report`` wrote for one study. NAME goes into
the task's name ("pointmaze-medium (mid)"), so two studies' pairs never pool: a quick and a mid
run of one seed start from different pre-trainings, and a pooled mean would describe neither
size. Prints the report's paired table (the same statistics) and writes the report's
difference figure (mean, bootstrap CI, t-interval per task, method and alpha; the noise floor
in grey).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from botorl.experiments.pairs import Pair, difference_figure, paired_markdown, paired_table, read_pairs_csv


def sized_pairs(studies: list[str]) -> list[Pair]:
    """The pairs of each ``NAME=PATH``, their task named "TASK (NAME)"."""
    pairs = []
    for study in studies:
        name, sep, path = study.partition("=")
        if not sep or not name or not path:
            raise SystemExit(f"{study!r}: give each study as NAME=PATH, e.g. quick=docs/results/.../paired.csv")
        pairs += [dataclasses.replace(p, task=f"{p.task} ({name})") for p in read_pairs_csv(Path(path))]
    return pairs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("studies", nargs="+", metavar="NAME=PATH", help="a study's name and its paired.csv")
    parser.add_argument("--out", type=Path, required=True, help="the figure (.png)")
    parser.add_argument("--bootstrap", type=int, default=2000)
    parser.add_argument("--confidence", type=float, default=0.95)
    args = parser.parse_args()
    pairs = sized_pairs(args.studies)
    order = {task: i for i, task in enumerate(dict.fromkeys(p.task for p in pairs))}  # the studies as given
    cells = sorted(paired_table(pairs, n_boot=args.bootstrap, confidence=args.confidence), key=lambda c: order[c.task])
    print(paired_markdown(cells, args.confidence, quantities=("dip", "success_10k")))
    difference_figure(cells, args.out, confidence=args.confidence, quantities=("dip",))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

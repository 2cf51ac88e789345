"""The whole study (4 tasks x 6 methods, 8 seeds each) in one table and one dip figure, put
together from the per-task reports `botorl report` wrote under docs/results/.

    python docs/results/study.py            # writes docs/results/study/{overview.md,dip.png}

Nothing is recomputed: the success means and the dip's statistics (mean, s.e., bootstrap CI,
IQM) are the `table1.csv` columns each report wrote, each run's dip (the figure's grey dots)
comes from the report's `dip_runs.csv`, and the figure is the report's own `dip_figure`. The study's
run directories of the medium and umaze BOTO/WSRL rows did not survive the machine they ran
on, so one `botorl report` over all of them cannot be rerun here; `botorl sweep ... --out
study/all && botorl report study/all` (docs/results/index.md) is that single report for a fresh study.
"""

from __future__ import annotations

import csv
from collections import defaultdict
from pathlib import Path

from botorl.experiments.dip import DipCell, dip_figure
from botorl.experiments.runs import from_scratch
from botorl.io import atomic_write_text

HERE = Path(__file__).resolve().parent
# the reports that hold the study's cells; each (task, method) is in exactly one of them
REPORTS = [
    "pointmaze-umaze", "pointmaze-umaze-baselines",
    "pointmaze-medium", "pointmaze-medium-cql-iql",
    "pointmaze-large",
    "door-binary-local",
]
TASKS = ["pointmaze-umaze", "pointmaze-medium", "pointmaze-large", "door-binary-local"]
METHODS = ["boto+calql", "wsrl", "calql", "cql", "iql", "rlpd"]
NAMES = {"boto+calql": "BOTO", "wsrl": "WSRL", "calql": "Cal-QL", "cql": "CQL", "iql": "IQL", "rlpd": "RLPD"}


def read(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def main() -> None:
    table: dict[tuple[str, str], dict] = {}
    runs: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for name in REPORTS:
        for r in read(HERE / name / "table1.csv"):
            key = (r["task"], r["method"])
            if key in table:
                raise SystemExit(f"{key} is in two reports ({name} and another): list each cell once")
            table[key] = r
        for r in read(HERE / name / "dip_runs.csv"):
            runs[(r["task"], r["method"])].append(r)

    cells = []
    lines = ["| task | method | seeds | success at 0 | dip, mean ± s.e. [95% CI] | 10k | final |",
             "|---|---|---|---|---|---|---|"]
    for task in TASKS:
        for method in METHODS:
            if (task, method) not in table:
                lines.append(f"| {task} | {NAMES[method]} | 0 | not measured | | | |")
                continue
            t, rs = table[(task, method)], runs[(task, method)]
            values = [float(r["dip"]) for r in rs]
            st = {k: float(t[f"dip_{k}"]) for k in ("mean", "se", "n", "lo", "hi", "iqm", "iqm_lo", "iqm_hi")}
            scratch = from_scratch(method.split("+")[0])
            cells.append(DipCell(task, NAMES[method], None, [int(r["seed"]) for r in rs], values,
                                 sum(float(r["success_0"]) for r in rs) / len(rs),
                                 sum(float(r["lowest"]) for r in rs) / len(rs), st, from_scratch=scratch))
            dip = f"{st['mean']:+.2f} ± {st['se']:.2f} [{st['lo']:+.2f}, {st['hi']:+.2f}]" + (" (no pre-training)" if scratch else "")
            ms = lambda k: f"{float(t[k + '_mean']):.2f} ± {float(t[k + '_se']):.2f}"  # noqa: E731
            lines.append(f"| {task} | {NAMES[method]} | {len(rs)} | {ms('initial')} | {dip} | {ms('10k')} | {ms('final')} |")

    out = HERE / "study"
    out.mkdir(exist_ok=True)
    atomic_write_text(out / "overview.md", "\n".join(lines) + "\n")
    dip_figure(cells, out / "dip.png", window=10_000, confidence=0.95)
    print("\n".join(lines))


if __name__ == "__main__":
    main()

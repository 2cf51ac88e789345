"""The ablation study's analysis, as its plan fixes it (docs/results/why-boto.md):

    python benchmarks/why_boto.py docs/results/why-boto/b*/paired.csv [--out DIR]

Reads the ``paired.csv`` file each block's ``botorl report`` wrote: a row is one run (an arm)
against WSRL from one pre-training, a file is one block, so arms pair within a file, never
across files (two machines' seed 200 are two pre-trainings). Every arm is against WSRL in the
file; (b) − (d) and the BOTO floor (f2) − (b) are differences of two such rows of one seed.

For the 5 primary comparisons x 2 endpoints (dip, success at 10k): the mean paired
difference, a pooled 95% bootstrap CI, a 95% block bootstrap CI (whole blocks resampled), the
t-interval, better / equal / worse, the two-sided Wilcoxon p and Holm's correction across the
10 tests. For the floors: the mean, SD and 2.5-97.5% range of their paired differences.
Writes ``why_boto.md`` (the tables) and ``why_boto.png`` (every arm's paired differences) to
``--out``.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from botorl.experiments.pairs import Pair, read_pairs_csv
from botorl.experiments.stats import (
    ZERO,
    bootstrap_mean_ci,
    fmt_ci,
    holm,
    pyplot,
    save_figure,
    t_interval,
    wilcoxon_signed_rank,
)

ENDPOINTS = ("dip", "success_10k")
# arm -> how its runs are labelled in paired.csv (label without variants, alpha, variant test)
ARMS = {
    "b": "BOTO alpha -1",
    "c": "BOTO alpha +1",
    "d": "re-fit control (no noise)",
    "e": "BOTO without the entropy term",
    "f1": "WSRL, online seed changed",
    "f2": "BOTO alpha -1, online seed changed",
}
PRIMARY = (("b", "a"), ("c", "a"), ("d", "a"), ("e", "a"), ("b", "d"))
FLOORS = (("f1", "a"), ("f2", "b"))
N_BOOT = 10_000


def arm_of(p: Pair) -> str | None:
    """Which arm a paired.csv row's other run is (None: a run the plan does not name)."""
    label = p.label
    variant = label.partition(" [")[2].rstrip("]")
    reseed = "online_reseed=1" in variant
    if label.startswith("wsrl"):
        return "f1" if reseed else None
    if not label.startswith("boto+calql"):
        return None
    if 'boto.noise="none"' in variant:
        return None if reseed or p.alpha != -1 else "d"
    if "boto.backup_entropy=false" in variant:
        return None if reseed or p.alpha != -1 else "e"
    if p.alpha == -1:
        return "f2" if reseed else "b"
    if p.alpha == 1 and not reseed:
        return "c"
    return None


@dataclass
class Diffs:
    """One comparison's paired differences on one endpoint, with the block of each."""

    values: np.ndarray
    blocks: np.ndarray


def table(paths: list[Path]) -> dict[tuple[str, str, int], dict[str, float]]:
    """{(block, arm, seed): the arm's endpoint values}, arm "a" (WSRL) from the reference side."""
    out: dict[tuple[str, str, int], dict[str, float]] = {}
    for path in paths:
        block = path.parent.name
        for p in read_pairs_csv(path):
            arm = arm_of(p)
            if arm is None:
                continue
            key = (block, arm, p.seed)
            if key in out:
                raise SystemExit(f"{path}: two rows for arm {arm} at seed {p.seed}; one run per arm and seed.")
            out[key] = dict(p.other)
            out.setdefault((block, "a", p.seed), dict(p.ref))
    return out


def differences(t: dict, x: str, y: str, endpoint: str) -> Diffs:
    """x − y per pre-training that ran both."""
    vals, blocks = [], []
    for (block, arm, seed), row in sorted(t.items()):
        if arm == x and (block, y, seed) in t:
            vals.append(row[endpoint] - t[(block, y, seed)][endpoint])
            blocks.append(block)
    return Diffs(np.asarray(vals, np.float64), np.asarray(blocks))


def block_bootstrap(d: Diffs, n_boot: int = N_BOOT, seed: int = 0) -> tuple[float, float]:
    """95% percentile CI of the mean when whole blocks are resampled (nan with < 2 blocks)."""
    names = sorted(set(d.blocks.tolist()))
    if len(names) < 2:
        return math.nan, math.nan
    groups = [d.values[d.blocks == b] for b in names]
    rng = np.random.default_rng(seed)
    means = []
    for _ in range(n_boot):
        pick = rng.integers(0, len(groups), len(groups))
        means.append(np.concatenate([groups[i] for i in pick]).mean())
    lo, hi = np.quantile(means, [0.025, 0.975])
    return float(lo), float(hi)


def name(arm: str) -> str:
    return "(a) WSRL" if arm == "a" else f"({arm}) {ARMS[arm]}"


def primary_rows(t: dict) -> list[dict]:
    rows = []
    for endpoint in ENDPOINTS:
        for x, y in PRIMARY:
            d = differences(t, x, y, endpoint)
            v = d.values
            rows.append({
                "endpoint": endpoint, "comparison": f"{name(x)} − {name(y)}", "n": len(v),
                "mean": float(v.mean()) if len(v) else math.nan,
                "boot": bootstrap_mean_ci(v, n_boot=N_BOOT), "block": block_bootstrap(d), "t": t_interval(v),
                "bew": (int((v > ZERO).sum()), int((abs(v) <= ZERO).sum()), int((v < -ZERO).sum())),
                "p": wilcoxon_signed_rank(v)[0],
            })
    for r, adj in zip(rows, holm([r["p"] for r in rows])):
        r["p_holm"] = adj
    return rows


def floor_rows(t: dict) -> list[dict]:
    rows = []
    for endpoint in ENDPOINTS:
        for x, y in FLOORS:
            v = differences(t, x, y, endpoint).values
            rows.append({"endpoint": endpoint, "comparison": f"{name(x)} − {name(y)}", "n": len(v),
                         "mean": float(v.mean()) if len(v) else math.nan,
                         "sd": float(v.std(ddof=1)) if len(v) > 1 else math.nan,
                         "range": tuple(np.quantile(v, [0.025, 0.975])) if len(v) else (math.nan, math.nan)})
    return rows


def _p(p: float) -> str:
    return "n/a" if not math.isfinite(p) else (f"{p:.4f}" if p >= 1e-4 else f"{p:.1e}")


def markdown(t: dict, primary: list[dict], floors: list[dict]) -> str:
    arms = sorted({arm for (_, arm, _) in t})
    blocks = sorted({b for (b, _, _) in t})
    means = []
    for arm in arms:
        rows = [v for (b, a, s), v in t.items() if a == arm]
        means.append(f"| {name(arm)} | {len(rows)} | " + " | ".join(
            f"{np.mean([r[e] for r in rows]):.2f}" for e in ("success_0", "lowest", *ENDPOINTS, "success_final")) + " |")
    lines = [f"Blocks: {', '.join(blocks)}.", "",
             "| arm | runs | success at 0 | lowest in window | dip | success at 10k | final |", "|---|---|---|---|---|---|---|",
             *means, "",
             "| endpoint | comparison | pairs | mean difference | 95% bootstrap CI | 95% block bootstrap | 95% t-interval "
             "| better / equal / worse | Wilcoxon p | Holm p |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in primary:
        lines.append(f"| {r['endpoint']} | {r['comparison']} | {r['n']} | {r['mean']:+.2f} | {fmt_ci(*r['boot'])} | "
                     f"{fmt_ci(*r['block'])} | {fmt_ci(*r['t'])} | {' / '.join(map(str, r['bew']))} | {_p(r['p'])} | "
                     f"{_p(r['p_holm'])} |")
    lines += ["", "| endpoint | noise floor | pairs | mean | SD | 2.5-97.5% range |", "|---|---|---|---|---|---|"]
    for r in floors:
        lines.append(f"| {r['endpoint']} | {r['comparison']} | {r['n']} | {r['mean']:+.2f} | {r['sd']:.2f} | "
                     f"{fmt_ci(*r['range'])} |")
    return "\n".join(lines) + "\n"


def figure(t: dict, path: Path) -> None:
    """Every comparison's paired differences (dots, one per pre-training) on both endpoints, with
    the floors' 2.5-97.5% ranges shaded."""
    plt = pyplot()
    comps = list(PRIMARY) + list(FLOORS)
    fig, axes = plt.subplots(1, len(ENDPOINTS), figsize=(11, 4.5), sharey=True)
    rng = np.random.default_rng(0)
    for ax, endpoint in zip(axes, ENDPOINTS):
        for i, (x, y) in enumerate(comps):
            v = differences(t, x, y, endpoint).values
            if len(v):
                ax.scatter(v + rng.uniform(-0.015, 0.015, len(v)), np.full(len(v), i) + rng.uniform(-0.2, 0.2, len(v)),
                           s=12, alpha=0.6, color="tab:gray" if (x, y) in FLOORS else "tab:blue")
                ax.plot([v.mean()], [i], "D", color="black", ms=6)
        for x, y in FLOORS:
            v = differences(t, x, y, endpoint).values
            if len(v) > 1:
                lo, hi = np.quantile(v, [0.025, 0.975])
                ax.axvspan(lo, hi, color="tab:gray", alpha=0.08)
        ax.axvline(0, color="black", lw=0.8)
        ax.set_title(endpoint.replace("_", " at ") if endpoint != "dip" else "dip (dense window)")
        ax.set_xlabel("paired difference")
    axes[0].set_yticks(range(len(comps)), [f"{name(x)} − {name(y)}" for x, y in comps], fontsize=7)
    save_figure(fig, path, "Why BOTO works: paired differences per pre-training (pointmaze-medium, quick)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("paired", nargs="+", type=Path, help="each block's paired.csv (from `botorl report`)")
    ap.add_argument("--out", type=Path, default=None, help="folder for why_boto.md and why_boto.png")
    args = ap.parse_args()
    t = table(args.paired)
    text = markdown(t, primary_rows(t), floor_rows(t))
    print(text)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "why_boto.md").write_text(text)
        figure(t, args.out / "why_boto.png")


if __name__ == "__main__":
    main()

"""Paired comparisons: runs that start from the same pre-training, compared pair by pair.

A pair is a run of the reference method (WSRL, ``online_reseed`` 0) and any other finished run
that starts from the same pre-trained agent: the same SHA-256 of its pre-training checkpoint
(``summary.json``'s ``pretrain_sha256``; runs older than that field are matched by the
pre-training fingerprint, ``pipeline.shared_pretrain.fingerprint_of``), so their difference is
the online phase alone. The same settings on another machine give another pre-training, which a
fingerprint cannot tell and the digest can; WSRL with another online seed gives the noise floor.
Pairing removes the spread between pre-trainings, most of the spread at 8-32 seeds of a nearly
binary success. The statistics per group and quantity: docs/running.md, "botorl report".
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from botorl.envs.metric import Metric
from botorl.experiments.dip import DIP_WINDOW, run_dip
from botorl.experiments.runs import Run, group_by, relative, to_float
from botorl.experiments.stats import (
    ZERO,
    alpha_text,
    bootstrap_mean_ci,
    check_bootstrap,
    csv_text,
    fmt_ci,
    fmt_float,
    md_table,
    mean_se,
    panels,
    pyplot,
    save_figure,
    t_interval,
    wilcoxon_signed_rank,
)
from botorl.io import CSV_LIMIT, atomic_write_text, csv_rows, read_bounded
from botorl.pipeline.shared_pretrain import fingerprint_of

REFERENCE = "wsrl"
# quantities compared, in the order of paired.csv (each: the reference's, the other's, other - reference)
QUANTITIES = ("success_0", "lowest", "dip", "success_10k", "success_final")
TABLE_QUANTITIES = ("dip", "success_10k", "success_final")  # shown in report.md


def _noise_floor(self) -> bool:
    """A pair's or cell's property: WSRL against WSRL (labels differ only in their variant)."""
    return self.label.split(" ")[0] == self.reference.split(" ")[0]


@dataclasses.dataclass
class Pair:
    task: str
    seed: int | None
    label: str  # the other run's label (boto+calql, wsrl [online_reseed=1], ...)
    alpha: float | None
    reference: str  # the reference run's label
    ref: dict[str, float]  # QUANTITIES of the reference run
    other: dict[str, float]  # QUANTITIES of the other run
    ref_path: str = ""
    other_path: str = ""

    def diff(self, q: str) -> float:
        return self.other[q] - self.ref[q]

    @property
    def group(self) -> tuple:
        """The group its statistics pool over, in the report's order (the noise floor last)."""
        return (self.task, self.noise_floor, self.label, -99 if self.alpha is None else self.alpha, self.reference)

    noise_floor = property(_noise_floor)


def canonical_label(label: str) -> str:
    """A run's label without ``online_reseed=0``: one block's "wsrl [online_reseed=0]" (its noise
    floor beside it) and another's plain "wsrl" are one method when pooled."""
    base, _, variant = label.partition(" [")
    parts = [v for v in variant.rstrip("]").split(", ") if v and v != "online_reseed=0"]
    return f"{base} [{', '.join(parts)}]" if parts else base


def _groups(pairs: Sequence[Pair]) -> list[list[Pair]]:
    groups = group_by(pairs, lambda p: p.group)
    return [groups[k] for k in sorted(groups)]


def _pretraining_key(run: Run) -> str | None:
    """The run's pre-training fingerprint as a string; None (never paired) when its config.json
    does not record the pre-training settings."""
    cfg = run.config
    if not run.pretrain or not all(isinstance(cfg.get(k), dict) for k in ("offline", "network", "data")):
        return None
    try:
        return json.dumps(fingerprint_of(cfg), sort_keys=True, default=str)
    except KeyError:
        return None


def _reseed(run: Run) -> int:
    v = run.config.get("online_reseed", 0)
    return v if isinstance(v, int) else 0


def _quantities(run: Run, window: float) -> dict[str, float] | None:
    if isinstance(d := run_dip(run, window), str):
        return None
    return {"success_0": d.initial, "lowest": d.lowest, "dip": d.value,
            "success_10k": run.success_10k, "success_final": run.success_final}


def _by_agent(runs: Sequence[Run], relative_to: Path | None) -> tuple[list[list[Run]], list[str]]:
    """The runs grouped by pre-training fingerprint, then checkpoint digest (runs without one form
    their own group); and a note for each fingerprint whose runs start from different agents."""
    groups: list[list[Run]] = []
    notes: list[str] = []
    for key, same_settings in group_by(runs, _pretraining_key).items():
        if key is None:
            continue
        by_digest = group_by(same_settings, lambda r: r.pretrain_sha256 or "")
        groups += by_digest.values()
        digests = {d: rs for d, rs in by_digest.items() if d}
        if len(digests) > 1:
            where = "; ".join(f"{d[:12]}: {', '.join(relative(r.path, relative_to) for r in rs[:3])}"
                              for d, rs in sorted(digests.items()))
            first = same_settings[0]
            notes.append(f"{sum(map(len, digests.values()))} runs have the pre-training settings of seed "
                         f"{first.seed} on {first.task} but start from {len(digests)} different pre-trained "
                         f"agents (checkpoint SHA-256; another machine or code makes another pre-training), so they "
                         f"are paired only within one agent ({where})")
    return groups, notes


def find_pairs(runs: Sequence[Run], *, reference: str = REFERENCE, window: float = DIP_WINDOW,
               relative_to: Path | None = None) -> tuple[list[Pair], list[str]]:
    """Every (reference run, other run) that start from the same pre-trained agent, and notes."""
    groups, notes = _by_agent(runs, relative_to)
    pairs: list[Pair] = []
    for group in groups:
        refs = [r for r in group if r.method == reference and _reseed(r) == 0]
        if not refs:
            continue
        ref = refs[0]
        if len(refs) > 1:
            notes.append(f"{len(refs)} {reference} runs share one pre-training ({', '.join(relative(r.path, relative_to) for r in refs)}); "
                         f"the others are paired with the first")
        ref_q, ref_path = _quantities(ref, window), relative(ref.path, relative_to)
        if ref_q is None:
            continue
        pairs += [Pair(ref.task, ref.seed, canonical_label(o.label), o.alpha if o.method == "boto" else None,
                       canonical_label(ref.label), ref_q, q, ref_path, relative(o.path, relative_to))
                  for o in group if o not in refs and (q := _quantities(o, window)) is not None]
    pairs.sort(key=lambda p: (*p.group, -1 if p.seed is None else p.seed))
    return pairs, notes


@dataclasses.dataclass
class PairedCell:
    task: str
    label: str
    alpha: float | None
    reference: str
    quantity: str
    n: int
    ref_mean: float
    other_mean: float
    mean: float  # mean difference other - reference
    se: float
    boot_lo: float
    boot_hi: float
    t_lo: float
    t_hi: float
    better: int
    equal: int
    worse: int
    wilcoxon_p: float
    wilcoxon_method: str  # 'exact', 'normal' (with ties) or 'none' (no nonzero difference)
    noise_floor = property(_noise_floor)


def paired_table(pairs: Sequence[Pair], *, quantities: Sequence[str] = QUANTITIES, n_boot: int = 2000,
                 confidence: float = 0.95, seed: int = 0) -> list[PairedCell]:
    cells = []
    for group in _groups(pairs):
        first = group[0]
        for q in quantities:
            d = [p.diff(q) for p in group]
            mean, se, n = mean_se(d)
            lo, hi = bootstrap_mean_ci(d, n_boot=n_boot, confidence=confidence, seed=seed)
            t_lo, t_hi = t_interval(d, confidence)
            fin = [v for v in d if math.isfinite(v)]
            cells.append(PairedCell(
                first.task, first.label, first.alpha, first.reference, q, n,
                mean_se([p.ref[q] for p in group])[0], mean_se([p.other[q] for p in group])[0],
                mean, se, lo, hi, t_lo, t_hi,
                sum(v > ZERO for v in fin), sum(abs(v) <= ZERO for v in fin), sum(v < -ZERO for v in fin),
                *wilcoxon_signed_rank(d),
            ))
    return cells


def pairs_csv(pairs: Sequence[Pair]) -> str:
    header = (["task", "seed", "method", "alpha", "reference"]
              + [f"{q}_{side}" for q in QUANTITIES for side in ("reference", "method", "diff")]
              + ["reference_path", "path"])
    return csv_text(header, ([p.task, "" if p.seed is None else p.seed, p.label,
                              "" if p.alpha is None else repr(p.alpha), p.reference]
                             + [fmt_float(v) for q in QUANTITIES for v in (p.ref[q], p.other[q], p.diff(q))]
                             + [p.ref_path, p.other_path] for p in pairs))


def read_pairs_csv(path: Path) -> list[Pair]:
    """The pairs a report wrote (``paired.csv``), to combine several reports' pairs."""
    with io.StringIO(read_bounded(path, CSV_LIMIT), newline="") as f:
        rows = csv_rows(f, path.name)[1]
    return [Pair(
            row["task"], int(row["seed"]) if row["seed"] else None, canonical_label(row["method"]),
            float(row["alpha"]) if row["alpha"] else None, canonical_label(row["reference"]),
            {q: to_float(row[f"{q}_reference"]) for q in QUANTITIES}, {q: to_float(row[f"{q}_method"]) for q in QUANTITIES},
            row.get("reference_path", ""), row.get("path", ""),
        ) for row in rows]


def paired_cells_csv(cells: Sequence[PairedCell]) -> str:
    fields = [f.name for f in dataclasses.fields(PairedCell)]
    return csv_text(fields, ([fmt_float(v) if isinstance(v, float) else ("" if v is None else v)
                              for v in (getattr(c, f) for f in fields)] for c in cells))


_NAMES = {"success_0": "success at 0", "lowest": "lowest in window", "dip": "dip", "success_10k": "success at 10k",
          "success_final": "final success"}


def _name(quantity: str, metric: Metric | None = None) -> str:
    """A quantity in words; on a task without success (``metric``) in its metric's words (the
    quantities keep their names in the CSV files)."""
    return _NAMES[quantity] if metric is None else _NAMES[quantity].replace("success", metric.label)


def paired_markdown(cells: Sequence[PairedCell], confidence: float, *,
                    quantities: Sequence[str] = TABLE_QUANTITIES, metrics: dict[str, Metric] | None = None) -> str:
    pct = f"{100 * confidence:g}%"
    return md_table(
        ["task", "method − reference", "alpha", "quantity", "pairs", "reference", "method", "mean difference",
         f"{pct} bootstrap CI", f"{pct} t-interval", "better / equal / worse", "Wilcoxon p"],
        ([c.task, f"{c.label} − {c.reference}" + (" (noise floor)" if c.noise_floor else ""), alpha_text(c.alpha),
          _name(c.quantity, (metrics or {}).get(c.task)), c.n, f"{c.ref_mean:.2f}", f"{c.other_mean:.2f}",
          f"{c.mean:+.3f}", fmt_ci(c.boot_lo, c.boot_hi, 3), fmt_ci(c.t_lo, c.t_hi, 3),
          f"{c.better} / {c.equal} / {c.worse}",
          "-" if not math.isfinite(c.wilcoxon_p) else f"{c.wilcoxon_p:.3f} ({c.wilcoxon_method})"]
         for c in cells if c.quantity in quantities))


def pairs_figure(pairs: Sequence[Pair], path: Path, *, quantity: str = "dip") -> Path:
    """One panel per group: each pair a line from the reference's value to the other's (jittered
    so that equal pairs stay visible); the path written."""
    groups = _groups(pairs)
    fig, axes = panels(len(groups), 3.2, 3.0, min(4, len(groups)), sharey=True)
    rng = np.random.default_rng(0)
    for ax, group in zip(axes.flat, groups):
        for p in group:
            j = rng.uniform(-0.015, 0.015)
            ax.plot([0, 1], [p.ref[quantity] + j, p.other[quantity] + j], "-o", ms=3, lw=0.8, alpha=0.6,
                    color="tab:green" if p.diff(quantity) > ZERO else "tab:red" if p.diff(quantity) < -ZERO
                    else "grey")
        mean, _, n = mean_se([p.diff(quantity) for p in group])
        ax.set_xticks([0, 1], [group[0].reference, group[0].label.replace(" [", "\n[")], fontsize=7)
        a = "" if group[0].alpha is None else f" α={group[0].alpha:+.2f}"
        ax.set_title(f"{group[0].task}{a}\nmean difference {mean:+.3f} (n={n})", fontsize=8)
        ax.set_xlim(-0.3, 1.3)
    axes[0][0].set_ylabel(_NAMES[quantity], fontsize=8)
    return save_figure(fig, path, f"Paired runs (same pre-training): {_NAMES[quantity]}, one line per pair; "
                                  "green: the method above the reference, red: below")


def difference_figure(cells: Sequence[PairedCell], path: Path, *, confidence: float = 0.95,
                      quantities: Sequence[str] = TABLE_QUANTITIES, metric: Metric | None = None) -> Path:
    """Per quantity, each group's mean paired difference with its bootstrap CI (thick) and
    t-interval (thin); the noise floor's rows in grey. The path written."""
    rows = [c for c in cells if c.quantity == quantities[0]]
    labels = [f"{c.task} {c.label}{'' if c.alpha is None else f' α={c.alpha:+.1f}'}" for c in rows]
    fig, axes = pyplot().subplots(1, len(quantities), figsize=(3.6 * len(quantities), 0.45 * len(rows) + 1.4),
                             squeeze=False, sharey=True)
    for ax, q in zip(axes[0], quantities):
        qc = {(c.task, c.label, c.alpha): c for c in cells if c.quantity == q}
        for y, r in enumerate(rows):
            c = qc[(r.task, r.label, r.alpha)]
            color = "grey" if c.noise_floor else "tab:blue"
            if math.isfinite(c.t_lo):
                ax.plot([c.t_lo, c.t_hi], [y, y], color=color, lw=1)
            if math.isfinite(c.boot_lo):
                ax.plot([c.boot_lo, c.boot_hi], [y, y], color=color, lw=4, alpha=0.6)
            ax.plot([c.mean], [y], "o", color=color)
        ax.axvline(0, color="black", lw=0.6)
        ax.set_title(f"{_name(q, metric)}, difference", fontsize=9)
        ax.tick_params(labelsize=7)
    axes[0][0].set_yticks(range(len(rows)), labels, fontsize=7)
    axes[0][0].invert_yaxis()
    reference = rows[0].reference if rows else "the reference"
    return save_figure(fig, path, f"Paired differences, method − {reference}: mean, {100 * confidence:g}% bootstrap "
                                  "CI (thick) and t-interval (thin); grey: the noise floor (the reference against "
                                  "itself, another online seed)")


def write_paired(pairs: Sequence[Pair], out: Path, *, n_boot: int, confidence: float, seed: int,
                 metrics: dict[str, Metric] | None = None) -> tuple[list[Path], list[str], list[PairedCell]]:
    """paired.csv, paired_table.csv, the two figures and the markdown section's lines
    (``metrics``: each task's headline metric, which the table names; success where not given)."""
    cells = paired_table(pairs, n_boot=n_boot, confidence=confidence, seed=seed)
    common = set((metrics or {}).values())  # the titles name the metric when every task has the same
    files = [atomic_write_text(out / "paired.csv", pairs_csv(pairs)),
             atomic_write_text(out / "paired_table.csv", paired_cells_csv(cells)),
             pairs_figure(pairs, out / "paired_dips.png"),
             difference_figure(cells, out / "paired_differences.png", confidence=confidence,
                               metric=common.pop() if len(common) == 1 else None)]
    pct = f"{100 * confidence:g}%"
    md = [
        "## Paired comparison (runs from the same pre-training)",
        "",
        "Each pair is a reference run and another run with the same pre-training fingerprint (task, seed, "
        "pre-training algorithm, data, networks, offline settings), so they differ only online. Differences are "
        f"method − reference: higher is better for every quantity. Mean with a {pct} percentile bootstrap CI "
        f"({n_boot} resamples of the pairs, seed {seed}) and a t-interval; counts of pairs better / equal / worse; "
        "two-sided Wilcoxon signed-rank p (zero differences dropped). The noise floor is the reference against "
        "itself with another online seed: a difference inside it is what chance alone makes. Per pair: "
        "`paired.csv`; every quantity: `paired_table.csv`.",
        "",
        paired_markdown(cells, confidence, metrics=metrics),
        "",
        "![paired differences](paired_differences.png)",
        "",
        "![paired dips](paired_dips.png)",
        "",
    ]
    return files, md, cells


def merge_pairs(pairs: Sequence[Pair], extra: Sequence[Pair]) -> list[Pair]:
    """``pairs`` and the ``extra`` ones (read from earlier reports) that are not among them."""
    have = {(p.task, p.seed, p.label, p.alpha, p.reference) for p in pairs}
    return list(pairs) + [p for p in extra if (p.task, p.seed, p.label, p.alpha, p.reference) not in have]


def write_paired_report(pairs: Sequence[Pair], out: Path, *, sources: Sequence[str] = (), n_boot: int = 2000,
                        confidence: float = 0.95, seed: int = 0) -> list[Path]:
    """A report of pairs alone (``botorl report --pairs-from``): the paired files and report.md."""
    check_bootstrap(n_boot, confidence)
    out.mkdir(parents=True, exist_ok=True)
    files, md, _ = write_paired(pairs, out, n_boot=n_boot, confidence=confidence, seed=seed)
    head = ["# botorl report: pairs", "", f"{len(pairs)} pairs from "
            + ", ".join(f"`{relative(s, out)}`" for s in sources) + ".", ""]
    atomic_write_text(out / "report.md", "\n".join(head + md))
    return files + [out / "report.md"]

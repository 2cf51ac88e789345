"""The dip: how far success falls early in fine-tuning (its definition: docs/running.md).

Per run, the lowest success over the evaluations with 0 <= env_step <= window minus the
success at step 0; per group, mean +- SE, the bootstrap CI of the mean and the IQM. On a task
without success, the same of its headline metric (the return or its normalised score;
``Run.metric``), in that metric's units.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from botorl.envs.metric import Metric
from botorl.experiments.runs import Run, Skipped, from_scratch, group_by, key_order, relative
from botorl.experiments.stats import (
    alpha_text,
    bootstrap_mean_ci,
    csv_text,
    fmt_ci,
    fmt_float,
    fmt_iqm,
    fmt_mean_se,
    label_colors,
    line_label,
    md_table,
    panels,
    pyplot,
    save_figure,
    seed_stats,
)

DIP_WINDOW = 10_000
DIP_KEYS = ("mean", "se", "n", "lo", "hi", "iqm", "iqm_lo", "iqm_hi")  # lo/hi: CI of the mean


@dataclasses.dataclass
class Dip:
    run: Run
    initial: float  # success at env_step 0
    lowest: float  # lowest success over 0 <= env_step <= window
    lowest_step: float  # the first env_step where it is reached
    evals: int  # evaluations inside the window, step 0 included
    last_step: float  # the last evaluation inside the window

    @property
    def value(self) -> float:
        return self.lowest - self.initial


def run_dip(run: Run, window: float = DIP_WINDOW) -> Dip | str:
    """The run's dip, or the reason it has none (Figure 5's evaluations: the step-0 value is
    summary.json's success_initial)."""
    steps, success = run.steps, run.success
    if steps.size == 0:
        return "eval.csv has no evaluations"
    if not np.any(steps == 0):
        return f"eval.csv has no evaluation at env_step 0 (the first is at {steps[0]:g}), so there is no start to dip from"
    inside = (steps >= 0) & (steps <= window)
    if run.dense_from is not None:
        # over step 0 and the dense points only, which every method shares (a baseline's
        # evaluations before the warm-up's end would give it more chances to dip)
        inside &= (steps == 0) | (steps >= run.dense_from)
    if int(inside.sum()) < 2:
        after = steps[steps > window]
        nxt = f" (the next is at {after[0]:g})" if after.size else ""
        return f"eval.csv has no evaluation after env_step 0 within the {window:g}-step dip window{nxt}"
    s_in, v_in = steps[inside], success[inside]
    k = int(np.argmin(v_in))
    return Dip(run, float(success[steps == 0][0]), float(v_in[k]), float(s_in[k]), int(inside.sum()), float(s_in[-1]))


def dips_of(runs: Sequence[Run], window: float) -> tuple[list[Dip], list[Skipped]]:
    """The runs' dips, and the runs without one (with the reason)."""
    found = [(r, run_dip(r, window)) for r in runs]
    return [d for _, d in found if isinstance(d, Dip)], [Skipped(r.path, d) for r, d in found if isinstance(d, str)]


@dataclasses.dataclass
class DipCell:
    task: str
    label: str
    alpha: float | None
    seeds: list[int | None]
    values: list[float]
    initial: float  # mean success at step 0 of these runs
    lowest: float  # mean lowest success in the window
    stats: dict[str, float]  # mean, se, n, lo, hi (CI of the mean), iqm, iqm_lo, iqm_hi
    from_scratch: bool = False  # no pre-training (rlpd): its dip is an untrained policy's, as dip_markdown says


def dip_table(dips: Sequence[Dip], *, n_boot: int, confidence: float, seed: int) -> list[DipCell]:
    groups = group_by(dips, lambda d: d.run.key)
    cells = []
    for key in sorted(groups, key=key_order):
        group = groups[key]
        values = [d.value for d in group]
        stats = seed_stats(values, n_boot=n_boot, confidence=confidence, seed=seed)
        stats["lo"], stats["hi"] = bootstrap_mean_ci(values, n_boot=n_boot, confidence=confidence, seed=seed)
        if stats["n"] < 2:  # resampling one run gives a zero-width interval, which would read as certainty
            stats["iqm_lo"] = stats["iqm_hi"] = math.nan
        cells.append(DipCell(
            *key, [d.run.seed for d in group], values,
            float(np.mean([d.initial for d in group])), float(np.mean([d.lowest for d in group])), stats,
            from_scratch=all(from_scratch(d.run.method) for d in group),
        ))
    return cells


def dip_runs_csv(dips: Sequence[Dip], relative_to: Path | None = None, metric: str = "success") -> str:
    """One row per run; paths relative to ``relative_to`` (the report's folder) when given;
    ``metric`` names the step-0 column (``<metric>_0``)."""
    header = ["task", "method", "alpha", "seed", f"{metric.replace(' ', '_')}_0", "lowest", "lowest_step", "evals_in_window",
              "last_step_in_window", "dip", "path"]
    return csv_text(header, ([d.run.task, d.run.label, "" if d.run.alpha is None else repr(d.run.alpha),
                              "" if d.run.seed is None else d.run.seed, fmt_float(d.initial), fmt_float(d.lowest),
                              f"{d.lowest_step:g}", d.evals, f"{d.last_step:g}", fmt_float(d.value),
                              relative(d.run.path, relative_to)] for d in dips))


def dip_markdown(cells: Sequence[DipCell], window: float, confidence: float, metric: str = "success") -> str:
    pct = f"{100 * confidence:g}%"
    lines = [md_table(
        ["task", "method", "alpha", "runs", f"{metric} at 0", f"lowest (0..{window:g})", "dip mean ± s.e.",
         f"{pct} CI of the mean", f"IQM [{pct} CI]"],
        ([c.task, c.label, alpha_text(c.alpha), int(c.stats["n"]), f"{c.initial:.2f}", f"{c.lowest:.2f}",
          fmt_mean_se(c.stats, "+"), fmt_ci(c.stats["lo"], c.stats["hi"]), fmt_iqm(c.stats, "+")] for c in cells))]
    scratch = sorted({(c.task, c.label) for c in cells if c.from_scratch})
    if scratch:
        lines.append("")
        lines += [f"{label} on {task} trains from scratch (no pre-training): its step-0 {metric} is an untrained "
                  "policy's, so its dip is that policy's luck at step 0, not unlearning." for task, label in scratch]
    return "\n".join(lines)


def dip_figure(cells: Sequence[DipCell], path: Path, *, window: float, confidence: float,
               metrics: dict[str, Metric] | None = None) -> Path:
    """Per task and group: the mean dip with its bootstrap CI, each run's dip a dot beside it
    (``metrics``: each task's headline metric; success where not given); the path written."""
    plt = pyplot()
    tasks = list(dict.fromkeys(c.task for c in cells))  # in the cells' order (dip_table sorts them)
    most = max(sum(1 for c in cells if c.task == t) for t in tasks)
    fig, axes = panels(len(tasks), max(3.6, 1.0 + 0.55 * most), 3.8, 2 if len(tasks) == 4 else None)
    colors = label_colors(c.label for c in cells)
    for ax, task in zip(axes.flat, tasks):
        row = [c for c in cells if c.task == task]
        multi = {lab: sum(1 for c in row if c.label == lab) > 1 for lab in {c.label for c in row}}
        for x, c in enumerate(row):
            st = c.stats
            color = plt.cm.coolwarm((c.alpha + 1.0) / 2.0) if multi[c.label] and c.alpha is not None else colors[c.label]
            # the runs, spread a little sideways (fixed offsets: the figure is reproducible)
            offsets = np.linspace(-0.18, 0.18, len(c.values)) if len(c.values) > 1 else np.zeros(1)
            ax.plot(x + 0.25 + offsets * 0.5, c.values, ".", color="0.55", ms=3, zorder=2)
            yerr = [[max(st["mean"] - st["lo"], 0.0)], [max(st["hi"] - st["mean"], 0.0)]] if math.isfinite(st["lo"]) else None
            ax.errorbar([x], [st["mean"]], yerr=yerr, fmt="o", color=color, ms=6, mec="0.2", capsize=4, lw=1.6,
                        ecolor="0.2" if multi[c.label] else color, zorder=3)
        ax.axhline(0.0, color="0.3", lw=0.8)
        ax.set_xticks(range(len(row)), [line_label(c.label, c.alpha, multi[c.label])
                                        + ("\n(no pre-training)" if c.from_scratch else "")
                                        + f"\n(n={int(c.stats['n'])})" for c in row],
                      rotation=45 if len(row) > 4 else 0, ha="right" if len(row) > 4 else "center", fontsize=7)
        ax.set_xlim(-0.6, len(row) - 0.4)
        metric = (metrics or {}).get(task, Metric())
        if metric.bounded:  # a return's dip has no fixed scale
            ax.set_ylim(-1.05, 0.08)
        ax.set_title(task)
        ax.set_ylabel(f"dip (lowest {metric.label} in 0..{window / 1000:g}k − {metric.label} at 0)", fontsize=8)
        ax.grid(alpha=0.3, axis="y")
    return save_figure(fig, path, f"The dip: mean over runs with {100 * confidence:g}% bootstrap CI; grey dots are "
                                  "single runs", dpi=120)

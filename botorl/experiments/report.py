"""``botorl report``: Table 1, the IQM table, Figure 5, the dip, paired comparisons, alpha
sensitivity and held-out alpha selection, from the finished runs ``runs.find_runs`` reads
(the others are listed as skipped, with the reason)."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
from collections import Counter
from functools import partial
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from botorl.configs.schema import flatten
from botorl.envs.metric import Metric
from botorl.errors import BotorlError, ConfigError, DataFormatError
from botorl.experiments.dip import (
    DIP_KEYS,
    DIP_WINDOW,
    Dip,
    DipCell,
    dip_figure,
    dip_markdown,
    dip_runs_csv,
    dip_table,
    dips_of,
    run_dip,
)
from botorl.experiments.pairs import Pair, PairedCell, find_pairs, merge_pairs, write_paired
from botorl.experiments.runs import Run, Skipped, find_runs, group_by, key_order, relative
from botorl.experiments.stats import (
    alpha_text,
    bootstrap_mean_ci,
    check_bootstrap,
    csv_text,
    fmt_float,
    fmt_iqm,
    fmt_mean_se,
    label_colors,
    line_label,
    md_table,
    mean_se,
    panels,
    pyplot,
    save_figure,
    seed_stats,
    stratified_bootstrap_iqm,
)
from botorl.io import atomic_write_text, own_folder
from botorl.pipeline.provenance import comparable

POINTS = (("initial", "success_initial"), ("10k", "success_10k"), ("final", "success_final"))
SELECT_ALPHA_CRITERION = (
    "highest mean over seeds of (success_10k + success_final) / 2; ties (within 1e-9) go to "
    "the smaller |alpha|, then to the smaller alpha"
)


def task_metrics(runs: Sequence[Run]) -> dict[str, Metric]:
    """Each task's headline metric (its first run's: the task records it in every run's config)."""
    return {task: rs[0].metric for task, rs in group_by(runs, lambda r: r.task).items()}


def metric_words(runs: Sequence[Run]) -> tuple[str, str]:
    """(what Table 1 and the figures are in, what the dip measures), in words."""
    metrics = list(task_metrics(runs).values())
    names = {m.name for m in metrics}
    if names <= {"success"}:
        return "success rate", "success"
    if len(names) == 1:
        return metrics[0].label, metrics[0].label
    return "the headline metric of each task", "headline metric"


def metric_lines(metrics: dict[str, Metric]) -> list[str]:
    """report.md's lines naming each task's metric (``task_metrics``); none when every task has success."""
    if all(m.name == "success" for m in metrics.values()):
        return []
    return ["Metric per task (success where the task defines it, else the return or its normalised score):", ""] + \
        [f"- {task}: {m.describe()}" for task, m in sorted(metrics.items())] + [""]


@dataclasses.dataclass
class Cell:
    task: str
    label: str
    alpha: float | None
    seeds: list[int | None]
    stats: dict[str, dict[str, float]]  # point -> mean, se, n, iqm, iqm_lo, iqm_hi
    dip: dict[str, float] | None = None  # DipCell.stats of the runs that have a dip


def table1(
    runs: Sequence[Run], *, n_boot: int, confidence: float, seed: int, dips: Sequence[DipCell] = ()
) -> list[Cell]:
    dip_by_key = {(d.task, d.label, d.alpha): d.stats for d in dips}
    groups = group_by(runs, lambda r: r.key)
    cells = []
    for task, label, alpha in sorted(groups, key=key_order):
        group = groups[(task, label, alpha)]
        stats = {point: seed_stats([getattr(r, fieldname) for r in group], n_boot=n_boot, confidence=confidence,
                                   seed=seed) for point, fieldname in POINTS}
        cells.append(Cell(task, label, alpha, [r.seed for r in group], stats, dip_by_key.get((task, label, alpha))))
    return cells


@dataclasses.dataclass
class Aggregate:
    label: str
    tasks: list[str]
    stats: dict[str, dict[str, float]]  # point -> iqm, iqm_lo, iqm_hi, n


def aggregate_iqm(runs: Sequence[Run], *, n_boot: int, confidence: float, seed: int) -> tuple[list[Aggregate], list[str]]:
    """IQM over all tasks per method, bootstrap stratified by task (rliable's aggregate)."""
    metrics = task_metrics(runs)
    out, notes = [], []
    by_label = group_by(runs, lambda r: r.label)
    for label in sorted(by_label):
        by_task = group_by(by_label[label], lambda r: r.task)
        swept = sorted(t for t, rs in by_task.items() if len({r.alpha if r.method == "boto" else None for r in rs}) > 1)
        if swept:
            notes.append(
                f"{label}: no aggregate, it has several alphas on {', '.join(swept)} (an alpha "
                "sweep); pick one per task with --select-alpha and report those runs."
            )
            continue
        tasks = sorted(by_task)
        scales = {metrics[t].name for t in tasks}
        if len(tasks) > 1 and not scales <= {"success"} and scales != {"score"}:
            notes.append(
                f"{label}: no aggregate over {', '.join(tasks)}: returns of different tasks are on different "
                "scales; give the tasks ref_min_score and ref_max_score to aggregate their normalised scores."
            )
            continue
        stats = {}
        for point, fieldname in POINTS:
            per_task = [[getattr(r, fieldname) for r in by_task[t]] for t in tasks]
            value, lo, hi = stratified_bootstrap_iqm(per_task, n_boot=n_boot, confidence=confidence, seed=seed)
            n = sum(1 for s in per_task for v in s if math.isfinite(v))
            stats[point] = {"iqm": value, "iqm_lo": lo, "iqm_hi": hi, "n": n}
        out.append(Aggregate(label, tasks, stats))
    return out, notes


CELL_KEYS = ("mean", "se", "n", "iqm", "iqm_lo", "iqm_hi")


def _csv_value(st: dict[str, float], k: str):
    return st["n"] if k == "n" else fmt_float(st.get(k, math.nan))


def cells_csv(cells: Sequence[Cell]) -> str:
    header = ["task", "method", "alpha", "seeds"] + [f"{p}_{k}" for p, _ in POINTS for k in CELL_KEYS]
    rows = ([c.task, c.label, "" if c.alpha is None else repr(c.alpha), " ".join(str(s) for s in c.seeds)]
            + [_csv_value(c.stats[p], k) for p, _ in POINTS for k in CELL_KEYS]
            + [_csv_value(c.dip or {"n": 0}, k) for k in DIP_KEYS] for c in cells)
    return csv_text(header + [f"dip_{k}" for k in DIP_KEYS], rows)


def aggregate_csv(aggs: Sequence[Aggregate]) -> str:
    keys = ("iqm", "iqm_lo", "iqm_hi", "n")
    header = ["method", "tasks"] + [f"{p}_{k}" for p, _ in POINTS for k in keys]
    rows = ([a.label, " ".join(a.tasks)] + [_csv_value(a.stats[p], k) for p, _ in POINTS for k in keys] for a in aggs)
    return csv_text(header, rows)


def cells_markdown(cells: Sequence[Cell]) -> str:
    return md_table(["task", "method", "alpha", "seeds", "initial (t=0)", "unlearning (t=10k)", "final"],
                    ([c.task, c.label, alpha_text(c.alpha), len(c.seeds), *(fmt_mean_se(c.stats[p]) for p, _ in POINTS)]
                     for c in cells))


def iqm_markdown(cells: Sequence[Cell], aggs: Sequence[Aggregate], confidence: float) -> str:
    table = md_table(["task", "method", "alpha", f"IQM initial [{100 * confidence:g}% CI]", "IQM 10k", "IQM final"],
                     ([c.task, c.label, alpha_text(c.alpha), *(fmt_iqm(c.stats[p]) for p, _ in POINTS)] for c in cells))
    return "\n".join([table] + [f"| **all ({len(a.tasks)} task{'s' if len(a.tasks) != 1 else ''})** | {a.label} | | "
                                + " | ".join(fmt_iqm(a.stats[p]) for p, _ in POINTS) + " |" for a in aggs])


def curve_on_grid(run: Run, grid: np.ndarray) -> np.ndarray:
    """Linear interpolation of one run's eval curve; nan outside the steps it evaluated."""
    out = np.full(grid.shape, np.nan)
    if run.steps.size == 0:
        return out
    inside = (grid >= run.steps[0]) & (grid <= run.steps[-1])
    out[inside] = np.interp(grid[inside], run.steps, run.success)
    return out


def mean_se_curves(curves: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per grid point: mean, SE (ddof=1; 0 where fewer than 2 runs) and run count."""
    finite = np.isfinite(curves)
    count = finite.sum(axis=0)
    mean = np.where(count > 0, np.where(finite, curves, 0.0).sum(axis=0) / np.maximum(count, 1), np.nan)
    dev = np.where(finite, curves - mean, 0.0)
    var = np.where(count >= 2, (dev**2).sum(axis=0) / np.maximum(count - 1, 1), 0.0)
    se = np.sqrt(var) / np.sqrt(np.maximum(count, 1))
    return mean, se, count


def figure5(runs: Sequence[Run], path: Path, *, grid_points: int = 101) -> Path:
    plt = pyplot()
    metrics = task_metrics(runs)
    tasks = sorted({r.task for r in runs})
    groups = group_by(runs, lambda r: r.key)
    crowded = max(sum(1 for k in groups if k[0] == t) for t in tasks) > 6 if tasks else False
    width = 4.6 + (2.2 if crowded else 0.0)  # room for a legend beside each panel
    fig, axes = panels(len(tasks), width, 3.5)
    colors = label_colors(k[1] for k in groups)
    for ax, task in zip(axes.flat, tasks):
        keys = sorted((k for k in groups if k[0] == task), key=key_order)
        per_label = {lab: [k for k in keys if k[1] == lab] for lab in {k[1] for k in keys}}
        max_step = max(float(r.steps[-1]) for k in keys for r in groups[k] if r.steps.size) if keys else 0.0
        grid = np.linspace(0.0, max(max_step, 1.0), grid_points)
        for key in keys:
            curves = np.stack([curve_on_grid(r, grid) for r in groups[key]])
            mean, se, count = mean_se_curves(curves)
            ok = count > 0
            sweep = len(per_label[key[1]]) > 1
            # an alpha sweep: blue (alpha -1) to red (alpha +1); a line beside a sweep: dashed
            color = plt.cm.coolwarm(((0.0 if key[2] is None else key[2]) + 1.0) / 2.0) if sweep else colors[key[1]]
            style = "--" if not sweep and len(per_label) < len(keys) else "-"
            name = line_label(key[1], key[2], sweep) + f" (n={len(groups[key])})"
            ax.plot(grid[ok], mean[ok], style, color=color, label=name, lw=1.6)
            ax.fill_between(grid[ok], (mean - se)[ok], (mean + se)[ok], color=color, alpha=0.2, lw=0)
        ax.set_title(task)
        ax.set_xlabel("online env steps")
        ax.xaxis.set_major_formatter(lambda x, _: f"{x / 1000:g}k" if x else "0")
        ax.set_ylabel("success rate" if metrics[task].bounded else metrics[task].label)
        if metrics[task].bounded:
            ax.set_ylim(-0.03, 1.03)
        ax.grid(alpha=0.3)
        if len(keys) > 6:
            ax.legend(fontsize=6, loc="upper left", bbox_to_anchor=(1.0, 1.0))
        else:
            ax.legend(fontsize=7, loc="best")
    what = metric_words(runs)[1]
    return save_figure(fig, path, f"{what[0].upper() + what[1:]} during online fine-tuning (mean ± standard error "
                                  "over seeds)", dpi=120)


@dataclasses.dataclass
class AlphaRow:
    task: str
    label: str
    alpha: float
    n: int
    stats: dict[str, tuple[float, float]]  # field -> (mean, s.e.) over seeds


ALPHA_FIELDS = ("success_initial", "success_10k", "success_final", "dip")


def alpha_table(runs: Sequence[Run], window: float = DIP_WINDOW) -> list[AlphaRow]:
    """Per (task, boto label, alpha) of a sweep of at least two alphas: mean ± s.e. over seeds of
    the success at 0, 10k and final and of the dip (nan for a run without one)."""
    sweeps = group_by([r for r in runs if r.method == "boto" and r.alpha is not None], lambda r: (r.task, r.label))
    rows = []
    for (task, label), sweep in sorted(sweeps.items()):
        by_alpha = group_by(sweep, lambda r: r.alpha)
        if len(by_alpha) < 2:
            continue
        for a, rs in sorted(by_alpha.items()):
            vals = {f: [getattr(r, f) for r in rs] for f in ALPHA_FIELDS[:3]}
            vals["dip"] = [d.value if isinstance(d := run_dip(r, window), Dip) else float("nan") for r in rs]
            rows.append(AlphaRow(task, label, a, len(rs), {f: mean_se(v)[:2] for f, v in vals.items()}))
    return rows


def alpha_csv(rows: Sequence[AlphaRow]) -> str:
    # csv quoting: a label names its variant settings joined by ", " (runs.py)
    head = ["task", "method", "alpha", "n"] + [f"{f}_{k}" for f in ALPHA_FIELDS for k in ("mean", "se")]
    return csv_text(head, ([r.task, r.label, f"{r.alpha:g}", str(r.n)] + [f"{x:.6g}" for f in ALPHA_FIELDS for x in r.stats[f]]
                           for r in rows))


def alpha_figure(rows: Sequence[AlphaRow], path: Path, *, window: float = DIP_WINDOW,
                 metrics: dict[str, Metric] | None = None) -> Path | None:
    """Per task: success (``metrics``: the task's headline metric) at 10k and final against alpha
    (top), the dip (bottom); the path written, None without a sweep."""
    if not rows:
        return None
    tasks = sorted({r.task for r in rows})
    fig, axes = pyplot().subplots(2, len(tasks), figsize=(4.6 * len(tasks), 6.4), squeeze=False, sharex=True)
    for col, task in enumerate(tasks):
        top, bottom = axes[0, col], axes[1, col]
        for label in sorted({r.label for r in rows if r.task == task}):
            rs = [r for r in rows if r.task == task and r.label == label]
            alphas = [r.alpha for r in rs]

            def series(field):
                m, se = np.array([r.stats[field] for r in rs]).T
                return m, np.where(np.isfinite(se), se, 0.0)

            points = [("success_10k", "10k", "--"), ("success_final", "final", "-")]
            if np.allclose(series("success_10k")[0], series("success_final")[0], equal_nan=True):
                points = [("success_final", "10k = final", "-")]
            for field, point, style in points:
                m, se = series(field)
                top.errorbar(alphas, m, yerr=se, fmt="o" + style, ms=3, capsize=2, label=f"{label} @ {point}")
            m, se = series("dip")
            bottom.errorbar(alphas, m, yerr=se, fmt="o-", ms=3, capsize=2, label=label)
        top.set_title(task)
        metric = (metrics or {}).get(task, Metric())
        top.set_ylabel("success rate" if metric.bounded else metric.label)
        if metric.bounded:
            top.set_ylim(-0.03, 1.03)
            bottom.set_ylim(-1.03, 0.03)
        bottom.set_ylabel(f"dip (lowest in 0..{window:g} - at 0)")
        bottom.set_xlabel("alpha")
        for ax in (top, bottom):
            ax.set_xlim(-1.05, 1.05)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
    return save_figure(fig, path, "Alpha sensitivity (mean ± standard error over seeds)", dpi=120)


def seeds_text(seeds: Iterable[int]) -> str:
    """[0, 1, 2, 3, 6] -> '0-3,6'."""
    ordered = sorted(set(seeds))
    spans = [[s for _, s in g] for _, g in itertools.groupby(enumerate(ordered), lambda x: x[1] - x[0])]
    return ",".join(str(g[0]) if len(g) == 1 else f"{g[0]}-{g[-1]}" for g in spans) or "none"


@dataclasses.dataclass
class AlphaChoice:
    task: str
    label: str
    alpha: float
    score: float  # held-out: mean score of the chosen alpha on its report seeds
    se: float
    lo: float  # bootstrap CI of that mean
    hi: float
    n: int  # held-out runs
    select_seeds: list[int]  # the chosen alpha's seeds that took part in choosing
    report_seeds: list[int]  # its held-out seeds, whose score is reported
    in_sample: float  # its score on its selection seeds (what picked it; flattering)
    in_sample_n: int
    ranking: list[tuple[float, float, int]]  # (alpha, selection score, n), best first


@dataclasses.dataclass
class AlphaSelection:
    choices: list[AlphaChoice]
    split: str = ""  # how the seeds were split, in words
    confidence: float = 0.95
    n_boot: int = 2000

    def text(self) -> str:
        if not self.choices:
            return (
                "# select-alpha: no finished boto runs with an explicit alpha were found; run an "
                "alpha sweep first (botorl sweep --methods boto --alphas -1:1:0.1 ...)."
            )
        pct = f"{100 * self.confidence:g}%"
        lines = [
            f"# alpha per task, criterion: {SELECT_ALPHA_CRITERION}",
            f"# held out: the criterion ranks the alphas on the selection seeds only; the chosen alpha's score "
            f"is then reported on its report seeds (disjoint). {self.split}",
            f"# held-out score: mean ± s.e. with a {pct} percentile-bootstrap CI of the mean "
            f"({self.n_boot} resamples); in-sample: the same alpha on the seeds that chose it",
        ]
        labels_per_task = Counter(c.task for c in self.choices)  # one choice per (task, label)
        for c in self.choices:
            runner_up = ""
            if len(c.ranking) > 1:
                a2, s2, _ = c.ranking[1]
                runner_up = f"; next alpha = {a2:g} ({s2:.3f} in selection)"
            which = f"{c.label}: " if labels_per_task[c.task] > 1 else ""
            se = f" ± {c.se:.3f}" if math.isfinite(c.se) else ""
            ci = f", {pct} CI [{c.lo:.3f}, {c.hi:.3f}]" if math.isfinite(c.lo) else f", no CI from {c.n} seed"
            lines.append(
                f"{c.task}: alpha = {c.alpha:g}  # {which}chosen on seeds {seeds_text(c.select_seeds)}, "
                f"reported on seeds {seeds_text(c.report_seeds)}: held-out score {c.score:.3f}{se}{ci} (n={c.n}); "
                f"in-sample {c.in_sample:.3f} (n={c.in_sample_n}); {len(c.ranking)} alphas tried{runner_up}"
            )
        return "\n".join(lines)


def _score(r: Run) -> float:
    return (r.success_10k + r.success_final) / 2


def select_alpha(runs: Sequence[Run], *, select_seeds: Sequence[int] | None = None,
                 report_seeds: Sequence[int] | None = None, n_boot: int = 2000, confidence: float = 0.95,
                 seed: int = 0) -> AlphaSelection:
    """Choose alpha per (task, boto label) on selection seeds, report it on held-out seeds (the
    winner's score on the runs that chose it overstates it: the winner is partly the luckiest);
    by default each alpha's sorted seeds, the first len // 2 select. BotorlError when an alpha
    has fewer than 2 seeds, the sets overlap, or one of them is empty for an alpha."""
    if select_seeds is None and report_seeds is not None:
        raise ConfigError("--report-seeds needs --select-seeds (the seeds that choose alpha).")
    sel_set = None if select_seeds is None else set(int(x) for x in select_seeds)
    rep_set = None if report_seeds is None else set(int(x) for x in report_seeds)
    if sel_set is not None and rep_set is not None and sel_set & rep_set:
        raise ConfigError(
            f"--select-seeds and --report-seeds share seeds {seeds_text(sel_set & rep_set)}; a seed "
            "that chooses alpha cannot also report its score. Give disjoint sets (e.g. --select-seeds 0-3 "
            "--report-seeds 4-7) or leave out --report-seeds to report on every other seed.")
    if sel_set is None:
        split = "Seeds: each alpha's seeds sorted by value, the first half (n // 2) selects and the rest reports."
    else:
        split = (f"Seeds: {seeds_text(sel_set)} select (--select-seeds), "
                 + (f"{seeds_text(rep_set)} report (--report-seeds)." if rep_set is not None
                    else "every other seed reports."))
    sweeps = group_by([r for r in runs if r.method == "boto" and r.alpha is not None
                       and math.isfinite(r.success_10k) and math.isfinite(r.success_final)], lambda r: (r.task, r.label))
    choices = []
    for (task, label), sweep in sorted(sweeps.items()):
        sel_runs: dict[float, list[Run]] = {}
        rep_runs: dict[float, list[Run]] = {}
        for a, rs in sorted(group_by(sweep, lambda r: r.alpha).items()):
            where = f"{task} / {label} alpha {a:+.2f}"
            if unseeded := [str(r.path) for r in rs if r.seed is None]:
                raise DataFormatError(
                    f"{where}: run(s) {', '.join(unseeded)} name no seed in "
                    "summary.json or config.json, so they cannot be split into selection and report seeds.")
            seeds = sorted({r.seed for r in rs})
            if len(seeds) < 2:
                raise ConfigError(
                    f"{where} has {len(seeds)} finished seed(s) "
                    f"({seeds_text(seeds)}); held-out alpha selection needs at least 2 per alpha (some seeds choose "
                    "alpha, others report its score). Run more seeds of every alpha (botorl sweep ... --seeds 0-7) "
                    "or leave the under-seeded alpha's runs out of the report directories.")
            chosen = set(seeds[: len(seeds) // 2]) if sel_set is None else set(seeds) & sel_set
            held = set(seeds) & rep_set if rep_set is not None else set(seeds) - chosen
            for name, got in (("selection", chosen), ("report", held)):
                if not got:
                    raise ConfigError(
                        f"{where} has seeds {seeds_text(seeds)}, none of them in the "
                        f"{name} set ({split}) Choose --select-seeds/--report-seeds so that every alpha has seeds "
                        "in both.")
            sel_runs[a] = [r for r in rs if r.seed in chosen]
            rep_runs[a] = [r for r in rs if r.seed in held]
        scored = [(a, float(np.mean([_score(r) for r in rs])), len(rs)) for a, rs in sel_runs.items()]
        best = max(x[1] for x in scored)
        # exact ties are common (success rates are multiples of 1/episodes): prefer small |alpha|,
        # i.e. the least biased critic among equally good ones
        scored.sort(key=lambda x: (0 if best - x[1] <= 1e-9 else 1, -x[1], abs(x[0]), x[0]))
        a, in_sample, in_sample_n = scored[0]
        held_scores = [_score(r) for r in rep_runs[a]]
        mean, se, n = mean_se(held_scores)
        lo, hi = bootstrap_mean_ci(held_scores, n_boot=n_boot, confidence=confidence, seed=seed)
        choices.append(AlphaChoice(
            task, label, a, mean, se, lo, hi, n,
            sorted({r.seed for r in sel_runs[a]}), sorted({r.seed for r in rep_runs[a]}), in_sample, in_sample_n, scored,
        ))
    return AlphaSelection(choices, split, confidence, n_boot)


@dataclasses.dataclass
class ReportResult:
    out: Path
    runs: list[Run]
    skipped: list[Skipped]
    files: list[Path]
    notes: list[str]
    dip_cells: list[DipCell]
    pairs: list[Pair]
    paired: list[PairedCell]
    no_dip: list[Skipped]  # finished runs without a dip
    selection: AlphaSelection | None  # None when held-out selection was impossible (see notes)

    def summary_text(self) -> str:
        return "\n".join([f"botorl report: {len(self.runs)} finished runs, {len(self.skipped)} skipped -> {self.out}"]
                         + [f"  skipped {s.path}: {s.reason}" for s in self.skipped]
                         + [f"  no dip for {s.path}: {s.reason}" for s in self.no_dip]
                         + [f"  note: {note}" for note in self.notes] + [f"  wrote {f}" for f in self.files])


def environment_notes(runs: Sequence[Run], rel) -> list[str]:
    """A note when the runs were made in more than one environment (config.json's ``environment``:
    botorl commit, package versions, CPU, XLA settings, backend), naming what differs."""
    records = {r.path: r.config.get("environment") for r in runs if isinstance(r.config.get("environment"), dict)}
    kinds = group_by(list(records), lambda p: comparable(records[p]))
    notes = []
    if len(kinds) > 1:
        flat = [flatten(json.loads(k)) for k in kinds]
        differ = sorted(k for k in set().union(*flat) if len({json.dumps(f.get(k)) for f in flat}) > 1)
        notes.append(f"the runs were made in {len(kinds)} environments (they differ in {', '.join(differ[:6])}"
                     f"{' ...' if len(differ) > 6 else ''}); e.g. {', '.join(rel(ps[0]) for ps in kinds.values())}")
    missing = len(runs) - len(records)
    if records and missing:
        notes.append(f"{missing} run(s) record no environment (made before botorl recorded it)")
    return notes


def make_report(dirs: Sequence[Path], out: Path, *, n_boot: int = 2000, confidence: float = 0.95, seed: int = 0,
                grid_points: int = 101, dip_window: float = DIP_WINDOW, select_seeds: Sequence[int] | None = None,
                report_seeds: Sequence[int] | None = None, extra_pairs: Sequence[Pair] = (),
                root: Path | None = None) -> ReportResult:
    """The report of the finished runs under ``dirs`` in ``out``; ``root``: the directory reported
    on that holds ``out`` (``DIR/report``: ``DIR``), from which no folder down to ``out`` may be a
    link (io.own_folder), so the report is written under it; None: ``out`` is the user's own."""
    check_bootstrap(n_boot, confidence)
    if not (isinstance(dip_window, (int, float)) and math.isfinite(dip_window) and dip_window > 0):
        raise ConfigError(f"--dip-window must be a positive number of online env steps, got {dip_window!r}.")
    runs, skipped = find_runs(dirs)
    boot = dict(n_boot=n_boot, confidence=confidence, seed=seed)
    out = Path(out)
    own_folder(out if root is None else root, out)
    rel = partial(relative, base=out)
    files: list[Path] = []
    notes: list[str] = []
    dips, no_dip = dips_of(runs, dip_window)
    dip_cells = dip_table(dips, **boot)
    short = sorted({d.run.path for d in dips if d.run.steps[-1] < dip_window})
    if short:
        notes.append(
            f"{len(short)} run(s) end before the {dip_window:g}-step dip window (their dip covers only the steps "
            f"they evaluated): {', '.join(rel(x) for x in short[:5])}{' ...' if len(short) > 5 else ''}"
        )
    off = sorted({r.task for r in runs if isinstance(r.config.get("env"), dict) and r.config["env"].get("success_off")})
    if off:  # a task of one's own whose env reports no success (docs/own-task.md)
        notes.append(f"success is off on {', '.join(off)}: the env's info has no success key, so the report is in "
                     f"the return there (or its normalised score; see the metric per task above)")
    notes += environment_notes(runs, rel)
    metrics = task_metrics(runs)
    table_what, dip_what = metric_words(runs)
    cells = table1(runs, **boot, dips=dip_cells)
    pairs, pair_notes = find_pairs(runs, window=dip_window, relative_to=out)
    pairs = merge_pairs(pairs, extra_pairs)
    notes += pair_notes
    paired_files, paired_md, paired_cells = write_paired(pairs, out, **boot, metrics=metrics) if pairs else ([], [], [])
    files += paired_files
    aggs, agg_notes = aggregate_iqm(runs, **boot)
    notes += agg_notes
    for (task, label, alpha), group in sorted(group_by(runs, lambda r: r.key).items(), key=lambda kv: str(kv[0])):
        dupes = sorted((s for s, k in Counter(r.seed for r in group).items() if k > 1), key=str)
        if dupes:
            where = ", ".join(rel(r.path) for r in group if r.seed in dupes)
            notes.append(
                f"{task} / {label}{'' if alpha is None else f' alpha {alpha:+.2f}'}: seed(s) "
                f"{dupes} appear more than once ({where}); each run counts as one sample"
            )
    for name, text in (("table1.csv", cells_csv(cells)), ("aggregate_iqm.csv", aggregate_csv(aggs)),
                       ("dip_runs.csv", dip_runs_csv(dips, relative_to=out, metric=dip_what))):
        files.append(atomic_write_text(out / name, text))
    if runs:
        files.append(figure5(runs, out / "figure5.png", grid_points=grid_points))
        if dip_cells:
            files.append(dip_figure(dip_cells, out / "dip.png", window=dip_window, confidence=confidence,
                                    metrics=metrics))
        else:
            notes.append("no run has a dip (see the reasons): no dip figure")
        alpha_rows = alpha_table(runs, dip_window)
        if alpha_png := alpha_figure(alpha_rows, out / "alpha_sensitivity.png", window=dip_window, metrics=metrics):
            files += [alpha_png, atomic_write_text(out / "alpha_sensitivity.csv", alpha_csv(alpha_rows))]
        else:
            notes.append("no alpha sweep among the runs (boto with >= 2 alphas on a task): no alpha figure")
    else:
        notes.append("no finished runs: no figures")
    selection = None
    try:
        selection = select_alpha(runs, select_seeds=select_seeds, report_seeds=report_seeds, **boot)
    except BotorlError as err:
        notes.append(f"no held-out alpha selection: {err}")
    pct = f"{100 * confidence:g}%"
    md = [
        "# botorl report",
        "",
        f"{len(runs)} finished runs from {', '.join(rel(d) for d in dirs)}; {len(skipped)} skipped.",
        "",
        f"## Table 1: {table_what}, mean ± standard error over seeds",
        "",
        *metric_lines(metrics),
        "SE = sample standard deviation (ddof=1) / sqrt(n). `initial` is online step 0, `10k` "
        "the unlearning step, `final` the last evaluation (300k in the paper's budget).",
        "",
        cells_markdown(cells),
        "",
        f"## Interquartile mean with {pct} stratified-bootstrap CI",
        "",
        f"IQM and percentile bootstrap ({n_boot} resamples of runs within each task, seed {seed}) "
        "after Agarwal et al. 2021 (rliable). Rows in bold aggregate all tasks of a method.",
        "",
        iqm_markdown(cells, aggs, confidence),
        "",
        f"## The dip (first {dip_window:g} online env steps)",
        "",
        f"Per run: the lowest {dip_what} over every evaluation with 0 <= env_step <= {dip_window:g} (warm-up "
        f"evaluations and step 0 included) minus the {dip_what} at env_step 0; 0 = no drop, "
        + ("-1 = from always to never solved" if dip_what == "success" else "negative = a drop, in its units")
        + f". Per method: mean ± s.e., the {pct} percentile-bootstrap CI of the mean ({n_boot} "
        f"resamples of the runs, seed {seed}) and the IQM with its CI. Per-run values: `dip_runs.csv`; the "
        "group values are also the `dip_*` columns of `table1.csv`.",
        "",
        dip_markdown(dip_cells, dip_window, confidence, metric=dip_what) if dip_cells else "No run has a dip.",
        "",
    ]
    if no_dip:
        md += ["Finished runs without a dip:", ""] + [f"- `{rel(s.path)}`: {s.reason}" for s in no_dip] + [""]
    if (out / "dip.png") in files:
        md += ["![the dip](dip.png)", ""]
    md += paired_md
    if (out / "figure5.png") in files:
        md += ["## Figure 5", "", "![figure 5](figure5.png)", ""]
    if (out / "alpha_sensitivity.png") in files:
        md += ["## Alpha sensitivity", "", f"Per alpha, mean ± s.e. over seeds (`alpha_sensitivity.csv`): {dip_what} at "
               "0, 10k and final, and the dip.", "", "![alpha sensitivity](alpha_sensitivity.png)", ""]
        if selection is not None:
            md += ["Selected alpha, held out (`botorl report --select-alpha`):", "", "```", selection.text(), "```", ""]
    if skipped:
        md += ["## Skipped run directories", ""] + [f"- `{rel(s.path)}`: {s.reason}" for s in skipped] + [""]
    if notes:
        md += ["## Notes", ""] + [f"- {n}" for n in notes] + [""]
    files.insert(0, atomic_write_text(out / "report.md", "\n".join(md)))
    if selection is not None and selection.choices:
        files.append(atomic_write_text(out / "alpha_selection.txt", selection.text() + "\n"))
    # outputs of an earlier report into the same folder that this one does not replace would
    # read as this report's
    for stale in ("alpha_selection.txt", "dip.png", "alpha_sensitivity.png", "alpha_sensitivity.csv", "figure5.png"):
        if (out / stale) not in files:
            (out / stale).unlink(missing_ok=True)
    return ReportResult(out, runs, skipped, files, notes, dip_cells, pairs, paired_cells, no_dip, selection)

"""Table 1, Figure 5 and the alpha-sensitivity figure from finished run directories.

Statistics:
- mean +- standard error over seeds, SE = sample standard deviation (ddof=1) / sqrt(n), as
  the paper's Table 1 and Figure 5 report them ("standard error across five random seeds");
- the interquartile mean (IQM) with a percentile stratified-bootstrap confidence interval,
  following Agarwal et al. 2021, "Deep RL at the Edge of the Statistical Precipice" (rliable):
  IQM = mean of the scores left after cutting floor(n/4) from each end of the sorted scores
  (scipy.stats.trim_mean(x, 0.25), which rliable uses); the bootstrap resamples runs with
  replacement within each task (strata) and recomputes the IQM of all resampled scores.
  Written here from that description; no rliable code is used.

Only runs with summary.json status "finished" count; every other run directory found is
listed as skipped, with the reason, in the report and on stdout.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import os
from collections import defaultdict
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from botorl.errors import BotorlError
from botorl.io import atomic_save_figure, atomic_write_text

POINTS = (("initial", "success_initial"), ("10k", "success_10k"), ("final", "success_final"))
SELECT_ALPHA_CRITERION = (
    "highest mean over seeds of (success_10k + success_final) / 2; ties (within 1e-9) go to "
    "the smaller |alpha|, then to the smaller alpha"
)


# ---------------------------------------------------------------------------------------------
# Statistics


def mean_se(values: Sequence[float]) -> tuple[float, float, int]:
    """Mean and standard error (ddof=1) of the finite values; SE is nan for n < 2."""
    x = np.asarray([v for v in values if v is not None and math.isfinite(v)], dtype=np.float64)
    n = int(x.size)
    if n == 0:
        return math.nan, math.nan, 0
    mean = float(x.mean())
    se = float(x.std(ddof=1) / math.sqrt(n)) if n >= 2 else math.nan
    return mean, se, n


def iqm(values: Sequence[float] | np.ndarray, axis: int = -1) -> Any:
    """Interquartile mean: drop floor(n/4) scores from each end, average the rest."""
    x = np.sort(np.asarray(values, dtype=np.float64), axis=axis)
    n = x.shape[axis]
    if n == 0:
        return math.nan
    cut = int(0.25 * n)
    kept = np.take(x, np.arange(cut, n - cut), axis=axis)
    out = kept.mean(axis=axis)
    return float(out) if np.ndim(out) == 0 else out


def stratified_bootstrap_iqm(
    scores_per_task: Sequence[Sequence[float]],
    *,
    n_boot: int = 2000,
    confidence: float = 0.95,
    seed: int = 0,
) -> tuple[float, float, float]:
    """IQM of all scores, and a percentile CI resampling runs within each task."""
    strata = [np.asarray([v for v in s if v is not None and math.isfinite(v)], dtype=np.float64) for s in scores_per_task]
    strata = [s for s in strata if s.size]
    if not strata:
        return math.nan, math.nan, math.nan
    point = iqm(np.concatenate(strata))
    if n_boot <= 0:
        return point, math.nan, math.nan
    rng = np.random.default_rng(seed)
    resampled = [s[rng.integers(0, s.size, size=(n_boot, s.size))] for s in strata]
    boot = iqm(np.concatenate(resampled, axis=1), axis=1)
    lo, hi = np.quantile(boot, [(1 - confidence) / 2, 1 - (1 - confidence) / 2])
    return point, float(lo), float(hi)


# ---------------------------------------------------------------------------------------------
# Reading run directories


@dataclasses.dataclass
class Run:
    path: Path
    task: str
    method: str
    pretrain: str | None
    alpha: float | None
    seed: int | None
    profile: str | None
    success_initial: float
    success_10k: float
    success_final: float
    steps: np.ndarray  # online env steps of the evaluations (sorted, unique)
    success: np.ndarray

    @property
    def label(self) -> str:
        if self.method == "boto" and self.pretrain:
            return f"boto+{self.pretrain}"
        return self.method

    @property
    def key(self) -> tuple[str, str, float | None]:
        return (self.task, self.label, self.alpha if self.method == "boto" else None)

    def value(self, field: str) -> float:
        return getattr(self, field)


@dataclasses.dataclass
class Skipped:
    path: Path
    reason: str


def _num(v: Any) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return math.nan
    return f


def read_eval_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(env_step, success) with one value per step: the last row written for that step.

    Several stages may evaluate at env_step 0 (end of pre-training, end of BOTO); the last
    one is what fine-tuning starts from.
    """
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames is None or not {"env_step", "success"} <= set(reader.fieldnames):
            raise ValueError(f"{path.name} has no env_step/success columns (header {reader.fieldnames})")
        by_step: dict[float, float] = {}
        for row in reader:
            step, succ = _num(row.get("env_step")), _num(row.get("success"))
            if math.isfinite(step) and step >= 0 and math.isfinite(succ):
                by_step.pop(step, None)
                by_step[step] = succ
    steps = np.asarray(sorted(by_step), dtype=np.float64)
    return steps, np.asarray([by_step[s] for s in steps], dtype=np.float64)


def _load_run(run_dir: Path) -> Run | Skipped:
    try:
        summary = json.loads((run_dir / "summary.json").read_text())
        if not isinstance(summary, dict):
            raise ValueError("not a JSON object")
    except (OSError, ValueError) as err:
        return Skipped(run_dir, f"summary.json unreadable ({err})")
    status = summary.get("status")
    if status != "finished":
        error = f" ({summary['error']})" if summary.get("error") else ""
        return Skipped(run_dir, f"status is {status!r}, not 'finished'{error}")
    config: dict[str, Any] = {}
    try:
        loaded = json.loads((run_dir / "config.json").read_text())
        config = loaded if isinstance(loaded, dict) else {}
    except (OSError, ValueError):
        pass

    def field(name: str) -> Any:
        return summary[name] if summary.get(name) is not None else config.get(name)

    if not field("task") or not field("method"):
        return Skipped(run_dir, "summary.json and config.json name no task/method")
    eval_path = run_dir / "eval.csv"
    if not eval_path.exists():
        return Skipped(run_dir, "finished but eval.csv is missing")
    try:
        steps, success = read_eval_csv(eval_path)
    except (OSError, ValueError) as err:
        return Skipped(run_dir, f"eval.csv unreadable ({err})")
    alpha = field("alpha")
    seed = field("seed")
    return Run(
        path=run_dir,
        task=str(field("task")),
        method=str(field("method")),
        pretrain=None if field("pretrain") in (None, "") else str(field("pretrain")),
        alpha=None if alpha is None or not math.isfinite(_num(alpha)) else round(float(alpha), 6),
        seed=None if seed is None else int(seed),
        profile=field("profile"),
        success_initial=_num(summary.get("success_initial")),
        success_10k=_num(summary.get("success_10k")),
        success_final=_num(summary.get("success_final")),
        steps=steps,
        success=success,
    )


def _last_line(path: Path) -> str:
    try:
        lines = [ln.strip() for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return "(unreadable)"
    return lines[-1][:300] if lines else "(empty)"


def find_runs(dirs: Iterable[Path]) -> tuple[list[Run], list[Skipped]]:
    """Every run directory under `dirs` (a folder with summary.json, or with config.json and
    no summary yet), recursively; run directories are not searched further down."""
    runs: list[Run] = []
    skipped: list[Skipped] = []
    seen: set[Path] = set()
    for top in dirs:
        top = Path(top)
        if not top.is_dir():
            raise BotorlError(f"botorl report: {top} is not a directory.")
        for root, subdirs, files in os.walk(top):
            root_p = Path(root).resolve()
            if "summary.json" in files or ("config.json" in files and "eval.csv" in files):
                subdirs[:] = []
                if root_p in seen:
                    continue
                seen.add(root_p)
                if "summary.json" not in files:
                    skipped.append(Skipped(Path(root), "no summary.json (the run never got far enough to write one)"))
                    continue
                loaded = _load_run(Path(root))
                (runs if isinstance(loaded, Run) else skipped).append(loaded)
            elif "config.json" in files and "checkpoints" in subdirs:
                subdirs[:] = []
                if root_p not in seen:
                    seen.add(root_p)
                    skipped.append(Skipped(Path(root), "no summary.json (the run never got far enough to write one)"))
            elif "population.json" in files:  # a population: its members are run directories
                subdirs[:] = sorted(d for d in subdirs if not d.startswith(".") and d != "checkpoints")
            elif "sweep-trial.log" in files:  # a sweep trial whose `botorl run` failed before starting
                subdirs[:] = []
                if root_p not in seen:
                    seen.add(root_p)
                    last = _last_line(Path(root) / "sweep-trial.log")
                    skipped.append(Skipped(Path(root), f"the run never started; sweep-trial.log ends: {last}"))
            else:
                subdirs[:] = sorted(d for d in subdirs if not d.startswith("."))
    runs.sort(key=lambda r: (r.task, r.label, -99 if r.alpha is None else r.alpha, r.seed or 0))
    return runs, skipped


# ---------------------------------------------------------------------------------------------
# Tables


@dataclasses.dataclass
class Cell:
    task: str
    label: str
    alpha: float | None
    seeds: list[int | None]
    stats: dict[str, dict[str, float]]  # point -> mean, se, n, iqm, iqm_lo, iqm_hi


def _alpha_text(alpha: float | None) -> str:
    return "" if alpha is None else f"{alpha:+.2f}"


def _fmt_ms(mean: float, se: float, n: int) -> str:
    if n == 0:
        return "-"
    if not math.isfinite(se):
        return f"{mean:.2f} (n=1)"
    return f"{mean:.2f} ± {se:.2f}"


def _group(runs: Sequence[Run]) -> dict[tuple[str, str, float | None], list[Run]]:
    groups: dict[tuple[str, str, float | None], list[Run]] = defaultdict(list)
    for r in runs:
        groups[r.key].append(r)
    return dict(groups)


def table1(runs: Sequence[Run], *, n_boot: int, confidence: float, seed: int) -> list[Cell]:
    cells = []
    for (task, label, alpha), group in sorted(
        _group(runs).items(), key=lambda kv: (kv[0][0], kv[0][1], -99 if kv[0][2] is None else kv[0][2])
    ):
        stats: dict[str, dict[str, float]] = {}
        for point, fieldname in POINTS:
            values = [r.value(fieldname) for r in group]
            mean, se, n = mean_se(values)
            point_iqm, lo, hi = stratified_bootstrap_iqm([values], n_boot=n_boot, confidence=confidence, seed=seed)
            stats[point] = {"mean": mean, "se": se, "n": n, "iqm": point_iqm, "iqm_lo": lo, "iqm_hi": hi}
        cells.append(Cell(task, label, alpha, [r.seed for r in group], stats))
    return cells


@dataclasses.dataclass
class Aggregate:
    label: str
    tasks: list[str]
    stats: dict[str, dict[str, float]]  # point -> iqm, iqm_lo, iqm_hi, n


def aggregate_iqm(runs: Sequence[Run], *, n_boot: int, confidence: float, seed: int) -> tuple[list[Aggregate], list[str]]:
    """IQM over all tasks per method, bootstrap stratified by task (rliable's aggregate)."""
    by_label: dict[str, dict[str, set]] = defaultdict(lambda: defaultdict(set))
    for r in runs:
        by_label[r.label][r.task].add(r.alpha if r.method == "boto" else None)
    out, notes = [], []
    for label in sorted(by_label):
        swept = sorted(t for t, alphas in by_label[label].items() if len(alphas) > 1)
        if swept:
            notes.append(
                f"{label}: no aggregate, it has several alphas on {', '.join(swept)} (an alpha "
                "sweep); pick one per task with --select-alpha and report those runs."
            )
            continue
        tasks = sorted(by_label[label])
        stats = {}
        for point, fieldname in POINTS:
            per_task = [[r.value(fieldname) for r in runs if r.label == label and r.task == t] for t in tasks]
            value, lo, hi = stratified_bootstrap_iqm(per_task, n_boot=n_boot, confidence=confidence, seed=seed)
            stats[point] = {
                "iqm": value, "iqm_lo": lo, "iqm_hi": hi,
                "n": sum(1 for s in per_task for v in s if math.isfinite(v)),
            }
        out.append(Aggregate(label, tasks, stats))
    return out, notes


def _f(x: float) -> str:
    return "" if x is None or (isinstance(x, float) and not math.isfinite(x)) else repr(float(x))


def cells_csv(cells: Sequence[Cell]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    header = ["task", "method", "alpha", "seeds"]
    for point, _ in POINTS:
        header += [f"{point}_{k}" for k in ("mean", "se", "n", "iqm", "iqm_lo", "iqm_hi")]
    w.writerow(header)
    for c in cells:
        row = [c.task, c.label, "" if c.alpha is None else repr(c.alpha), " ".join(str(s) for s in c.seeds)]
        for point, _ in POINTS:
            st = c.stats[point]
            row += [_f(st["mean"]), _f(st["se"]), st["n"], _f(st["iqm"]), _f(st["iqm_lo"]), _f(st["iqm_hi"])]
        w.writerow(row)
    return buf.getvalue()


def aggregate_csv(aggs: Sequence[Aggregate]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    header = ["method", "tasks"]
    for point, _ in POINTS:
        header += [f"{point}_{k}" for k in ("iqm", "iqm_lo", "iqm_hi", "n")]
    w.writerow(header)
    for a in aggs:
        row = [a.label, " ".join(a.tasks)]
        for point, _ in POINTS:
            st = a.stats[point]
            row += [_f(st["iqm"]), _f(st["iqm_lo"]), _f(st["iqm_hi"]), st["n"]]
        w.writerow(row)
    return buf.getvalue()


def cells_markdown(cells: Sequence[Cell]) -> str:
    lines = [
        "| task | method | alpha | seeds | initial (t=0) | unlearning (t=10k) | final |",
        "|---|---|---|---|---|---|---|",
    ]
    for c in cells:
        parts = [_fmt_ms(c.stats[p]["mean"], c.stats[p]["se"], int(c.stats[p]["n"])) for p, _ in POINTS]
        lines.append(f"| {c.task} | {c.label} | {_alpha_text(c.alpha)} | {len(c.seeds)} | " + " | ".join(parts) + " |")
    return "\n".join(lines)


def _fmt_iqm(st: dict[str, float]) -> str:
    if not math.isfinite(st["iqm"]):
        return "-"
    if not math.isfinite(st["iqm_lo"]):
        return f"{st['iqm']:.2f}"
    return f"{st['iqm']:.2f} [{st['iqm_lo']:.2f}, {st['iqm_hi']:.2f}]"


def iqm_markdown(cells: Sequence[Cell], aggs: Sequence[Aggregate], confidence: float) -> str:
    pct = f"{100 * confidence:g}%"
    lines = [
        f"| task | method | alpha | IQM initial [{pct} CI] | IQM 10k | IQM final |",
        "|---|---|---|---|---|---|",
    ]
    for c in cells:
        lines.append(
            f"| {c.task} | {c.label} | {_alpha_text(c.alpha)} | "
            + " | ".join(_fmt_iqm(c.stats[p]) for p, _ in POINTS) + " |"
        )
    for a in aggs:
        lines.append(
            f"| **all ({len(a.tasks)} tasks)** | {a.label} | | "
            + " | ".join(_fmt_iqm(a.stats[p]) for p, _ in POINTS) + " |"
        )
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# Figures


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


def _line_label(label: str, alpha: float | None, multi_alpha: bool) -> str:
    if not multi_alpha:
        return label
    return f"{label} α=preset" if alpha is None else f"{label} α={alpha:+.2f}"


def figure5(runs: Sequence[Run], path: Path, *, grid_points: int = 101) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    tasks = sorted({r.task for r in runs})
    ncols = min(3, max(1, len(tasks)))
    nrows = math.ceil(len(tasks) / ncols)
    groups = _group(runs)
    crowded = max(sum(1 for k in groups if k[0] == t) for t in tasks) > 6 if tasks else False
    width = 4.6 + (2.2 if crowded else 0.0)  # room for a legend beside each panel
    fig, axes = plt.subplots(nrows, ncols, figsize=(width * ncols, 3.5 * nrows), squeeze=False)
    labels = sorted({k[1] for k in groups})
    colors = {lab: plt.cm.tab10(i % 10) for i, lab in enumerate(labels)}
    for ax, task in zip(axes.flat, tasks):
        keys = sorted((k for k in groups if k[0] == task), key=lambda k: (k[1], -99 if k[2] is None else k[2]))
        per_label = {lab: [k for k in keys if k[1] == lab] for lab in {k[1] for k in keys}}
        max_step = max(float(r.steps[-1]) for k in keys for r in groups[k] if r.steps.size) if keys else 0.0
        grid = np.linspace(0.0, max(max_step, 1.0), grid_points)
        for key in keys:
            curves = np.stack([curve_on_grid(r, grid) for r in groups[key]])
            mean, se, count = mean_se_curves(curves)
            ok = count > 0
            siblings = per_label[key[1]]
            style = "-"
            if len(siblings) > 1:  # an alpha sweep: blue (alpha -1) to red (alpha +1)
                alpha_value = 0.0 if key[2] is None else key[2]
                color = plt.cm.coolwarm((alpha_value + 1.0) / 2.0)
            else:
                color = colors[key[1]]
                if len(per_label) < len(keys):  # beside a sweep: dashed, to tell them apart
                    style = "--"
            name = _line_label(key[1], key[2], len(siblings) > 1) + f" (n={len(groups[key])})"
            ax.plot(grid[ok], mean[ok], style, color=color, label=name, lw=1.6)
            ax.fill_between(grid[ok], (mean - se)[ok], (mean + se)[ok], color=color, alpha=0.2, lw=0)
        ax.set_title(task)
        ax.set_xlabel("online env steps")
        ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x / 1000:g}k" if x else "0"))
        ax.set_ylabel("success rate")
        ax.set_ylim(-0.03, 1.03)
        ax.grid(alpha=0.3)
        if len(keys) > 6:
            ax.legend(fontsize=6, loc="upper left", bbox_to_anchor=(1.0, 1.0))
        else:
            ax.legend(fontsize=7, loc="best")
    for ax in list(axes.flat)[len(tasks):]:
        ax.set_visible(False)
    fig.suptitle("Success during online fine-tuning (mean ± standard error over seeds)", fontsize=10)
    fig.tight_layout()
    atomic_save_figure(fig, path, dpi=120)
    plt.close(fig)


def alpha_runs(runs: Sequence[Run]) -> dict[tuple[str, str], dict[float, list[Run]]]:
    """(task, boto label) -> alpha -> runs, for those with at least two alphas."""
    out: dict[tuple[str, str], dict[float, list[Run]]] = defaultdict(lambda: defaultdict(list))
    for r in runs:
        if r.method == "boto" and r.alpha is not None:
            out[(r.task, r.label)][r.alpha].append(r)
    return {k: dict(v) for k, v in out.items() if len(v) >= 2}


def alpha_figure(runs: Sequence[Run], path: Path) -> bool:
    """Success at 10k and final against alpha, one panel per task; False if no alpha sweep."""
    swept = alpha_runs(runs)
    if not swept:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = sorted({t for t, _ in swept})
    ncols = min(3, len(tasks))
    nrows = math.ceil(len(tasks) / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.6 * ncols, 3.5 * nrows), squeeze=False)
    for ax, task in zip(axes.flat, tasks):
        for (t, label), by_alpha in sorted(swept.items()):
            if t != task:
                continue
            alphas = sorted(by_alpha)
            for fieldname, point, style in (("success_10k", "10k", "--"), ("success_final", "final", "-")):
                stats = [mean_se([r.value(fieldname) for r in by_alpha[a]]) for a in alphas]
                mean = np.array([s[0] for s in stats])
                se = np.array([0.0 if not math.isfinite(s[1]) else s[1] for s in stats])
                ax.errorbar(alphas, mean, yerr=se, fmt="o" + style, ms=3, capsize=2, label=f"{label} @ {point}")
        ax.set_title(task)
        ax.set_xlabel("alpha")
        ax.set_ylabel("success rate")
        ax.set_xlim(-1.05, 1.05)
        ax.set_ylim(-0.03, 1.03)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(tasks):]:
        ax.set_visible(False)
    fig.suptitle("Alpha sensitivity (mean ± standard error over seeds)", fontsize=10)
    fig.tight_layout()
    atomic_save_figure(fig, path, dpi=120)
    plt.close(fig)
    return True


# ---------------------------------------------------------------------------------------------
# Alpha selection


@dataclasses.dataclass
class AlphaChoice:
    task: str
    label: str
    alpha: float
    score: float
    n: int
    ranking: list[tuple[float, float, int]]  # (alpha, score, n), best first


@dataclasses.dataclass
class AlphaSelection:
    choices: list[AlphaChoice]

    def text(self) -> str:
        if not self.choices:
            return (
                "# select-alpha: no finished boto runs with an explicit alpha were found; run an "
                "alpha sweep first (botorl sweep --methods boto --alphas -1:1:0.1 ...)."
            )
        lines = [f"# alpha per task, criterion: {SELECT_ALPHA_CRITERION}"]
        labels_per_task = defaultdict(set)
        for c in self.choices:
            labels_per_task[c.task].add(c.label)
        for c in self.choices:
            runner_up = ""
            if len(c.ranking) > 1:
                a2, s2, _ = c.ranking[1]
                runner_up = f"; next alpha = {a2:g} ({s2:.3f})"
            which = f"{c.label}: " if len(labels_per_task[c.task]) > 1 else ""
            lines.append(
                f"{c.task}: alpha = {c.alpha:g}  # {which}score {c.score:.3f} over {c.n} seeds, "
                f"{len(c.ranking)} alphas tried{runner_up}"
            )
        return "\n".join(lines)


def select_alpha(runs: Sequence[Run]) -> AlphaSelection:
    by: dict[tuple[str, str], dict[float, list[float]]] = defaultdict(lambda: defaultdict(list))
    for r in runs:
        if r.method != "boto" or r.alpha is None:
            continue
        if math.isfinite(r.success_10k) and math.isfinite(r.success_final):
            by[(r.task, r.label)][r.alpha].append((r.success_10k + r.success_final) / 2)
    choices = []
    for (task, label), per_alpha in sorted(by.items()):
        scored = [(a, float(np.mean(v)), len(v)) for a, v in per_alpha.items() if v]
        best = max(s for _, s, _ in scored)
        # exact ties are common (success rates are multiples of 1/episodes): prefer small |alpha|,
        # i.e. the least biased critic among equally good ones
        scored.sort(key=lambda x: (0 if best - x[1] <= 1e-9 else 1, -x[1], abs(x[0]), x[0]))
        a, s, n = scored[0]
        choices.append(AlphaChoice(task, label, a, s, n, scored))
    return AlphaSelection(choices)


# ---------------------------------------------------------------------------------------------
# The whole report


@dataclasses.dataclass
class ReportResult:
    out: Path
    runs: list[Run]
    skipped: list[Skipped]
    cells: list[Cell]
    aggregates: list[Aggregate]
    files: list[Path]
    notes: list[str]

    def summary_text(self) -> str:
        lines = [f"botorl report: {len(self.runs)} finished runs, {len(self.skipped)} skipped -> {self.out}"]
        for s in self.skipped:
            lines.append(f"  skipped {s.path}: {s.reason}")
        for note in self.notes:
            lines.append(f"  note: {note}")
        for f in self.files:
            lines.append(f"  wrote {f}")
        return "\n".join(lines)


def make_report(
    dirs: Sequence[Path],
    out: Path,
    *,
    n_boot: int = 2000,
    confidence: float = 0.95,
    seed: int = 0,
    grid_points: int = 101,
) -> ReportResult:
    runs, skipped = find_runs(dirs)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files: list[Path] = []
    notes: list[str] = []
    cells = table1(runs, n_boot=n_boot, confidence=confidence, seed=seed)
    aggs, agg_notes = aggregate_iqm(runs, n_boot=n_boot, confidence=confidence, seed=seed)
    notes += agg_notes
    for (task, label, alpha), group in sorted(_group(runs).items(), key=lambda kv: str(kv[0])):
        seeds = [r.seed for r in group]
        dupes = sorted({s for s in seeds if seeds.count(s) > 1}, key=str)
        if dupes:
            where = ", ".join(str(r.path) for r in group if r.seed in dupes)
            notes.append(
                f"{task} / {label}{'' if alpha is None else f' alpha {alpha:+.2f}'}: seed(s) "
                f"{dupes} appear more than once ({where}); each run counts as one sample"
            )
    atomic_write_text(out / "table1.csv", cells_csv(cells))
    atomic_write_text(out / "aggregate_iqm.csv", aggregate_csv(aggs))
    files += [out / "table1.csv", out / "aggregate_iqm.csv"]
    if runs:
        figure5(runs, out / "figure5.png", grid_points=grid_points)
        files.append(out / "figure5.png")
        if alpha_figure(runs, out / "alpha_sensitivity.png"):
            files.append(out / "alpha_sensitivity.png")
        else:
            notes.append("no alpha sweep among the runs (boto with >= 2 alphas on a task): no alpha figure")
    else:
        notes.append("no finished runs: no figures")
    selection = select_alpha(runs)
    md = [
        "# botorl report",
        "",
        f"{len(runs)} finished runs from {', '.join(str(d) for d in dirs)}; {len(skipped)} skipped.",
        "",
        "## Table 1: success rate, mean ± standard error over seeds",
        "",
        "SE = sample standard deviation (ddof=1) / sqrt(n). `initial` is online step 0, `10k` "
        "the unlearning step, `final` the last evaluation (300k in the paper's budget).",
        "",
        cells_markdown(cells),
        "",
        f"## Interquartile mean with {100 * confidence:g}% stratified-bootstrap CI",
        "",
        f"IQM and percentile bootstrap ({n_boot} resamples of runs within each task, seed {seed}) "
        "after Agarwal et al. 2021 (rliable). Rows in bold aggregate all tasks of a method.",
        "",
        iqm_markdown(cells, aggs, confidence),
        "",
    ]
    if (out / "figure5.png") in files:
        md += ["## Figure 5", "", "![figure 5](figure5.png)", ""]
    if (out / "alpha_sensitivity.png") in files:
        md += ["## Alpha sensitivity", "", "![alpha sensitivity](alpha_sensitivity.png)", ""]
        md += ["Selected alpha (`botorl report --select-alpha`):", "", "```", selection.text(), "```", ""]
    if skipped:
        md += ["## Skipped run directories", ""]
        md += [f"- `{s.path}`: {s.reason}" for s in skipped]
        md.append("")
    if notes:
        md += ["## Notes", ""] + [f"- {n}" for n in notes] + [""]
    atomic_write_text(out / "report.md", "\n".join(md))
    files.insert(0, out / "report.md")
    if selection.choices:
        atomic_write_text(out / "alpha_selection.txt", selection.text() + "\n")
        files.append(out / "alpha_selection.txt")
    return ReportResult(out, runs, skipped, cells, aggs, files, notes)

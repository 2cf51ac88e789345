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
- the dip: per run, the lowest success over every evaluation with
  0 <= env_step <= window (default 10,000; warm-up evaluations and step 0 included; for a run
  that evaluated densely (eval.dense_interval > 0), step 0 and the dense points from the
  warm-up's end only, the same points for every method) minus the success at env_step 0, so 0 is no drop and -1 a fall from always to never solving the task.
  Per group: mean +- SE, a percentile bootstrap CI of the mean (runs resampled with
  replacement) and the IQM with its CI as above. Runs without an evaluation at step 0, or
  with none after it inside the window, get no dip and are listed with the reason.

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

from botorl.errors import BotorlError, ConfigError, DataFormatError
from botorl.io import atomic_save_figure, atomic_write_text
from botorl.pipeline.methods import METHODS

POINTS = (("initial", "success_initial"), ("10k", "success_10k"), ("final", "success_final"))
DIP_WINDOW = 10_000
DIP_KEYS = ("mean", "se", "n", "lo", "hi", "iqm", "iqm_lo", "iqm_hi")  # lo/hi: CI of the mean
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


def bootstrap_mean_ci(
    values: Sequence[float], *, n_boot: int = 2000, confidence: float = 0.95, seed: int = 0
) -> tuple[float, float]:
    """Percentile bootstrap CI of the mean: resample the runs with replacement n_boot times.

    (nan, nan) for fewer than 2 finite values: one run says nothing about its spread."""
    x = np.asarray([v for v in values if v is not None and math.isfinite(v)], dtype=np.float64)
    if x.size < 2 or n_boot <= 0:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    boot = x[rng.integers(0, x.size, size=(n_boot, x.size))].mean(axis=1)
    lo, hi = np.quantile(boot, [(1 - confidence) / 2, 1 - (1 - confidence) / 2])
    return float(lo), float(hi)


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
    settings: dict[str, Any] = dataclasses.field(default_factory=dict)  # config.json, flattened (_settings)
    # the first step of the dense dip window (the warm-up's end) when the run evaluated densely
    # there (eval.dense_interval > 0), else None
    dense_from: float | None = None
    config: dict[str, Any] = dataclasses.field(default_factory=dict, repr=False)  # config.json as read
    variant: str = ""  # the settings in which this run differs from others of its method (label_variants)

    @property
    def label(self) -> str:
        base = f"boto+{self.pretrain}" if self.method == "boto" and self.pretrain else self.method
        return f"{base} [{self.variant}]" if self.variant else base

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


# Config fields that differ between runs of one method without making them another method:
# the member's identity (seed, alpha and their copies), where and how it logs, how updates are
# chunked into calls, and where its pre-training came from (the same numbers either way).
_SAME_METHOD = {"seed", "alpha", "out", "pretrained", "progress", "tensorboard", "wandb", "checkpoint_every",
                "boto.alpha", "boto.seed", "eval.num_envs", "offline.updates_per_call", "boto.steps_per_call",
                "offline.sample_on_device"}


def _settings(config: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in config.items():
        key = prefix + str(k)
        if isinstance(v, dict):
            out.update(_settings(v, key + "."))
        elif key not in _SAME_METHOD and not key.endswith("log_every"):
            out[key] = json.dumps(v, sort_keys=True)
    return out


def label_variants(runs: list[Run]) -> None:
    """Runs of one method on one task that differ in a setting (``--boto.train-actor``, another
    ``online.steps``) are different variants, not more seeds of one: each gets the settings in
    which its method's runs differ (on any task) appended to its label, e.g.
    ``boto+calql [boto.train_actor=true]``, so tables, curves and dips keep them apart."""
    by_method: dict[tuple[str, str], list[Run]] = defaultdict(list)
    for r in runs:
        by_method[(r.method, r.pretrain or "")].append(r)
    for group in by_method.values():
        varying: set[str] = set()
        by_task: dict[str, list[Run]] = defaultdict(list)
        for r in group:
            by_task[r.task].append(r)
        for same_task in by_task.values():
            keys = set().union(*(r.settings for r in same_task))
            varying |= {k for k in keys if len({r.settings.get(k) for r in same_task}) > 1}
        for r in group:
            r.variant = ", ".join(f"{k}={r.settings.get(k, 'null')}" for k in sorted(varying))


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
        settings=_settings(config),
        dense_from=_dense_from(config),
        config=config,
    )


def _dense_from(config: dict) -> float | None:
    ev, wu = config.get("eval"), config.get("warmup")
    if not isinstance(ev, dict) or not isinstance(wu, dict) or not _num(ev.get("dense_interval")) > 0:
        return None
    start = _num(wu.get("steps"))
    return start if math.isfinite(start) and start >= 0 else None


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
            raise BotorlError(f"{top} is not a directory.")
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
    label_variants(runs)
    runs.sort(key=lambda r: (r.task, r.label, -99 if r.alpha is None else r.alpha, r.seed or 0))
    return runs, skipped


# ---------------------------------------------------------------------------------------------
# The dip: how far success falls early in fine-tuning


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
    """The run's dip, or the reason it has none.

    Uses the run's evaluations as Figure 5 does (one per env_step, the last row written for a
    step), so the step-0 value is summary.json's success_initial."""
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
    dips: list[Dip] = []
    no_dip: list[Skipped] = []
    for r in runs:
        d = run_dip(r, window)
        if isinstance(d, Dip):
            dips.append(d)
        else:
            no_dip.append(Skipped(r.path, d))
    return dips, no_dip


def dip_stats(values: Sequence[float], *, n_boot: int, confidence: float, seed: int) -> dict[str, float]:
    mean, se, n = mean_se(values)
    lo, hi = bootstrap_mean_ci(values, n_boot=n_boot, confidence=confidence, seed=seed)
    point_iqm, iqm_lo, iqm_hi = stratified_bootstrap_iqm([values], n_boot=n_boot, confidence=confidence, seed=seed)
    if n < 2:  # resampling one run gives a zero-width interval, which would read as certainty
        iqm_lo = iqm_hi = math.nan
    return {"mean": mean, "se": se, "n": n, "lo": lo, "hi": hi, "iqm": point_iqm, "iqm_lo": iqm_lo, "iqm_hi": iqm_hi}


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
    # a method without pre-training (rlpd): its step 0 is an untrained policy, so its "dip" is
    # that policy's luck at step 0, not unlearning, and the report says so beside the number
    from_scratch: bool = False


def _from_scratch(method: str) -> bool:
    m = METHODS.get(method)
    return m is not None and not m.pretrains


def _key_order(key: tuple[str, str, float | None]) -> tuple:
    return (key[0], key[1], -99 if key[2] is None else key[2])


def dip_table(dips: Sequence[Dip], *, n_boot: int, confidence: float, seed: int) -> list[DipCell]:
    groups: dict[tuple[str, str, float | None], list[Dip]] = defaultdict(list)
    for d in dips:
        groups[d.run.key].append(d)
    cells = []
    for key in sorted(groups, key=_key_order):
        group = groups[key]
        values = [d.value for d in group]
        cells.append(DipCell(
            *key, [d.run.seed for d in group], values,
            float(np.mean([d.initial for d in group])), float(np.mean([d.lowest for d in group])),
            dip_stats(values, n_boot=n_boot, confidence=confidence, seed=seed),
            from_scratch=all(_from_scratch(d.run.method) for d in group),
        ))
    return cells


def dip_runs_csv(dips: Sequence[Dip]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["task", "method", "alpha", "seed", "success_0", "lowest", "lowest_step", "evals_in_window",
                "last_step_in_window", "dip", "path"])
    for d in dips:
        r = d.run
        w.writerow([r.task, r.label, "" if r.alpha is None else repr(r.alpha), "" if r.seed is None else r.seed,
                    _f(d.initial), _f(d.lowest), f"{d.lowest_step:g}", d.evals, f"{d.last_step:g}", _f(d.value),
                    str(r.path)])
    return buf.getvalue()


def _fmt_ci(lo: float, hi: float) -> str:
    return "-" if not math.isfinite(lo) else f"[{lo:+.2f}, {hi:+.2f}]"


def dip_markdown(cells: Sequence[DipCell], window: float, confidence: float) -> str:
    pct = f"{100 * confidence:g}%"
    lines = [
        f"| task | method | alpha | runs | success at 0 | lowest (0..{window:g}) | dip mean ± s.e. | "
        f"{pct} CI of the mean | IQM [{pct} CI] |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for c in cells:
        st = c.stats
        ms = "-" if st["n"] == 0 else (f"{st['mean']:+.2f} (n=1)" if not math.isfinite(st["se"])
                                       else f"{st['mean']:+.2f} ± {st['se']:.2f}")
        iq = "-" if not math.isfinite(st["iqm"]) else (f"{st['iqm']:+.2f}" + (
            f" {_fmt_ci(st['iqm_lo'], st['iqm_hi'])}" if math.isfinite(st["iqm_lo"]) else ""))
        lines.append(
            f"| {c.task} | {c.label} | {_alpha_text(c.alpha)} | {int(st['n'])} | {c.initial:.2f} | {c.lowest:.2f} | "
            f"{ms} | {_fmt_ci(st['lo'], st['hi'])} | {iq} |"
        )
    scratch = sorted({(c.task, c.label) for c in cells if c.from_scratch})
    if scratch:
        lines.append("")
        lines += [f"{label} on {task} trains from scratch (no pre-training): its step-0 success is an untrained "
                  "policy's, so its dip is that policy's luck at step 0, not unlearning." for task, label in scratch]
    return "\n".join(lines)


def dip_figure(cells: Sequence[DipCell], path: Path, *, window: float, confidence: float) -> None:
    """Per task, one point per method (and alpha): the mean dip with its bootstrap CI, and
    each run's dip as a small dot beside it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = list(dict.fromkeys(c.task for c in cells))  # in the cells' order (dip_table sorts them)
    ncols = 2 if len(tasks) == 4 else min(3, max(1, len(tasks)))
    nrows = math.ceil(len(tasks) / ncols)
    most = max(sum(1 for c in cells if c.task == t) for t in tasks)
    width = max(3.6, 1.0 + 0.55 * most)
    fig, axes = plt.subplots(nrows, ncols, figsize=(width * ncols, 3.8 * nrows), squeeze=False)
    labels = sorted({c.label for c in cells})
    colors = {lab: plt.cm.tab10(i % 10) for i, lab in enumerate(labels)}
    for ax, task in zip(axes.flat, tasks):
        row = [c for c in cells if c.task == task]
        multi = {lab: sum(1 for c in row if c.label == lab) > 1 for lab in {c.label for c in row}}
        for x, c in enumerate(row):
            st = c.stats
            color = plt.cm.coolwarm((c.alpha + 1.0) / 2.0) if multi[c.label] and c.alpha is not None else colors[c.label]
            # the runs, spread a little sideways (fixed offsets: the figure is reproducible)
            offsets = np.linspace(-0.18, 0.18, len(c.values)) if len(c.values) > 1 else np.zeros(1)
            ax.plot(x + 0.25 + offsets * 0.5, c.values, ".", color="0.55", ms=3, zorder=2)
            if math.isfinite(st["lo"]):
                yerr = [[max(st["mean"] - st["lo"], 0.0)], [max(st["hi"] - st["mean"], 0.0)]]
                ax.errorbar([x], [st["mean"]], yerr=yerr, fmt="o", color=color, ms=6, mec="0.2", capsize=4, lw=1.6,
                            ecolor="0.2" if multi[c.label] else color, zorder=3)
            else:
                ax.plot([x], [st["mean"]], "o", color=color, ms=6, mec="0.2", zorder=3)
        ax.axhline(0.0, color="0.3", lw=0.8)
        ax.set_xticks(range(len(row)))
        ax.set_xticklabels([_line_label(c.label, c.alpha, multi[c.label]) + ("\n(no pre-training)" if c.from_scratch else "")
                            + f"\n(n={int(c.stats['n'])})" for c in row],
                           rotation=45 if len(row) > 4 else 0, ha="right" if len(row) > 4 else "center", fontsize=7)
        ax.set_xlim(-0.6, len(row) - 0.4)
        ax.set_ylim(-1.05, 0.08)
        ax.set_title(task)
        ax.set_ylabel(f"dip (lowest success in 0..{window / 1000:g}k − success at 0)", fontsize=8)
        ax.grid(alpha=0.3, axis="y")
    for ax in list(axes.flat)[len(tasks):]:
        ax.set_visible(False)
    _suptitle(fig, f"The dip: mean over runs with {100 * confidence:g}% bootstrap CI; grey dots are single runs")
    fig.tight_layout()
    atomic_save_figure(fig, path, dpi=120)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------
# Tables


@dataclasses.dataclass
class Cell:
    task: str
    label: str
    alpha: float | None
    seeds: list[int | None]
    stats: dict[str, dict[str, float]]  # point -> mean, se, n, iqm, iqm_lo, iqm_hi
    dip: dict[str, float] | None = None  # dip_stats of the runs that have a dip


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


def table1(
    runs: Sequence[Run], *, n_boot: int, confidence: float, seed: int, dips: Sequence[DipCell] = ()
) -> list[Cell]:
    dip_by_key = {(d.task, d.label, d.alpha): d.stats for d in dips}
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
        cells.append(Cell(task, label, alpha, [r.seed for r in group], stats, dip_by_key.get((task, label, alpha))))
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
    header += [f"dip_{k}" for k in DIP_KEYS]
    w.writerow(header)
    for c in cells:
        row = [c.task, c.label, "" if c.alpha is None else repr(c.alpha), " ".join(str(s) for s in c.seeds)]
        for point, _ in POINTS:
            st = c.stats[point]
            row += [_f(st["mean"]), _f(st["se"]), st["n"], _f(st["iqm"]), _f(st["iqm_lo"]), _f(st["iqm_hi"])]
        dip = c.dip or {"n": 0}
        row += [dip["n"] if k == "n" else _f(dip.get(k, math.nan)) for k in DIP_KEYS]
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
            f"| **all ({len(a.tasks)} task{'s' if len(a.tasks) != 1 else ''})** | {a.label} | | "
            + " | ".join(_fmt_iqm(a.stats[p]) for p, _ in POINTS) + " |"
        )
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# Figures


def _suptitle(fig, text: str) -> None:
    """A figure title wrapped to the figure's width (a one-task figure is narrower than the line)."""
    import textwrap

    chars = max(20, int(fig.get_figwidth() * 11))  # ~11 characters an inch at 10 pt
    fig.suptitle("\n".join(textwrap.wrap(text, chars)), fontsize=10)


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
    _suptitle(fig, "Success during online fine-tuning (mean ± standard error over seeds)")
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


@dataclasses.dataclass
class AlphaRow:
    task: str
    label: str
    alpha: float
    n: int
    stats: dict[str, tuple[float, float]]  # field -> (mean, s.e.) over seeds


ALPHA_FIELDS = ("success_initial", "success_10k", "success_final", "dip")


def alpha_table(runs: Sequence[Run], window: float = DIP_WINDOW) -> list[AlphaRow]:
    """Per (task, boto label, alpha) of a sweep: mean ± s.e. over seeds of the success at 0,
    10k and final and of the dip (run_dip with ``window``; a run without one counts as nan)."""
    rows = []
    for (task, label), by_alpha in sorted(alpha_runs(runs).items()):
        for a in sorted(by_alpha):
            rs = by_alpha[a]
            vals = {f: [r.value(f) for r in rs] for f in ALPHA_FIELDS[:3]}
            vals["dip"] = [d.value if isinstance(d := run_dip(r, window), Dip) else float("nan") for r in rs]
            rows.append(AlphaRow(task, label, a, len(rs), {f: mean_se(v)[:2] for f, v in vals.items()}))
    return rows


def alpha_csv(rows: Sequence[AlphaRow]) -> str:
    head = ["task", "method", "alpha", "n"] + [f"{f}_{k}" for f in ALPHA_FIELDS for k in ("mean", "se")]
    lines = [",".join(head)]
    for r in rows:
        vals = [f"{x:.6g}" for f in ALPHA_FIELDS for x in r.stats[f]]
        lines.append(",".join([r.task, r.label, f"{r.alpha:g}", str(r.n)] + vals))
    return "\n".join(lines) + "\n"


def alpha_figure(rows: Sequence[AlphaRow], path: Path, *, window: float = DIP_WINDOW) -> bool:
    """Per task of a sweep: success at 10k and final against alpha (top) and the dip (bottom);
    False if there is no sweep. A sweep whose runs end at 10k plots one success curve."""
    if not rows:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = sorted({r.task for r in rows})
    fig, axes = plt.subplots(2, len(tasks), figsize=(4.6 * len(tasks), 6.4), squeeze=False, sharex=True)
    for col, task in enumerate(tasks):
        top, bottom = axes[0, col], axes[1, col]
        for label in sorted({r.label for r in rows if r.task == task}):
            rs = [r for r in rows if r.task == task and r.label == label]
            alphas = [r.alpha for r in rs]

            def series(field):
                m = np.array([r.stats[field][0] for r in rs])
                se = np.array([r.stats[field][1] for r in rs])
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
        top.set_ylabel("success rate")
        top.set_ylim(-0.03, 1.03)
        bottom.set_ylabel(f"dip (lowest in 0..{window:g} - at 0)")
        bottom.set_ylim(-1.03, 0.03)
        bottom.set_xlabel("alpha")
        for ax in (top, bottom):
            ax.set_xlim(-1.05, 1.05)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
    _suptitle(fig, "Alpha sensitivity (mean ± standard error over seeds)")
    fig.tight_layout()
    atomic_save_figure(fig, path, dpi=120)
    plt.close(fig)
    return True


# ---------------------------------------------------------------------------------------------
# Alpha selection
#
# Choosing the best of many alphas and reporting its score on the same runs overstates it (the
# winner is partly the luckiest). So each alpha's seeds are split: the selection seeds rank
# the alphas, and the chosen alpha's score is reported on its other, held-out seeds.


def seeds_text(seeds: Iterable[int]) -> str:
    """[0, 1, 2, 3, 6] -> '0-3,6'."""
    out: list[str] = []
    ordered = sorted(set(seeds))
    i = 0
    while i < len(ordered):
        j = i
        while j + 1 < len(ordered) and ordered[j + 1] == ordered[j] + 1:
            j += 1
        out.append(str(ordered[i]) if i == j else f"{ordered[i]}-{ordered[j]}")
        i = j + 1
    return ",".join(out) or "none"


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
        labels_per_task = defaultdict(set)
        for c in self.choices:
            labels_per_task[c.task].add(c.label)
        for c in self.choices:
            runner_up = ""
            if len(c.ranking) > 1:
                a2, s2, _ = c.ranking[1]
                runner_up = f"; next alpha = {a2:g} ({s2:.3f} in selection)"
            which = f"{c.label}: " if len(labels_per_task[c.task]) > 1 else ""
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


def select_alpha(
    runs: Sequence[Run],
    *,
    select_seeds: Sequence[int] | None = None,
    report_seeds: Sequence[int] | None = None,
    n_boot: int = 2000,
    confidence: float = 0.95,
    seed: int = 0,
) -> AlphaSelection:
    """Choose alpha per (task, boto label) on selection seeds, report it on held-out seeds.

    `select_seeds` None: each alpha's distinct seeds, sorted, split into a first half
    (len // 2, for selection) and the rest (for reporting). Given: those seeds select and
    `report_seeds` (default: every other seed) report. Raises BotorlError when an alpha has
    fewer than 2 seeds, when the two sets overlap, or when one of them is empty for an alpha.
    """
    if select_seeds is None and report_seeds is not None:
        raise ConfigError("--report-seeds needs --select-seeds (the seeds that choose alpha).")
    sel_set = None if select_seeds is None else set(int(x) for x in select_seeds)
    rep_set = None if report_seeds is None else set(int(x) for x in report_seeds)
    if sel_set is not None and rep_set is not None and sel_set & rep_set:
        raise ConfigError(
            f"--select-seeds and --report-seeds share seeds {seeds_text(sel_set & rep_set)}; a seed "
            "that chooses alpha cannot also report its score. Give disjoint sets (e.g. --select-seeds 0-3 "
            "--report-seeds 4-7) or leave out --report-seeds to report on every other seed."
        )
    if sel_set is None:
        split = "Seeds: each alpha's seeds sorted by value, the first half (n // 2) selects and the rest reports."
    else:
        split = (f"Seeds: {seeds_text(sel_set)} select (--select-seeds), "
                 + (f"{seeds_text(rep_set)} report (--report-seeds)." if rep_set is not None
                    else "every other seed reports."))
    by: dict[tuple[str, str], dict[float, list[Run]]] = defaultdict(lambda: defaultdict(list))
    for r in runs:
        if r.method != "boto" or r.alpha is None:
            continue
        if math.isfinite(r.success_10k) and math.isfinite(r.success_final):
            by[(r.task, r.label)][r.alpha].append(r)

    def where(task: str, label: str, alpha: float) -> str:
        return f"{task} / {label} alpha {alpha:+.2f}"

    choices = []
    for (task, label), per_alpha in sorted(by.items()):
        sel_runs: dict[float, list[Run]] = {}
        rep_runs: dict[float, list[Run]] = {}
        for a, rs in sorted(per_alpha.items()):
            unseeded = [str(r.path) for r in rs if r.seed is None]
            if unseeded:
                raise DataFormatError(
                    f"{where(task, label, a)}: run(s) {', '.join(unseeded)} name no seed in "
                    "summary.json or config.json, so they cannot be split into selection and report seeds."
                )
            seeds = sorted({r.seed for r in rs})
            if len(seeds) < 2:
                raise ConfigError(
                    f"{where(task, label, a)} has {len(seeds)} finished seed(s) "
                    f"({seeds_text(seeds)}); held-out alpha selection needs at least 2 per alpha (some seeds choose "
                    "alpha, others report its score). Run more seeds of every alpha (botorl sweep ... --seeds 0-7) "
                    "or leave the under-seeded alpha's runs out of the report directories."
                )
            if sel_set is None:
                chosen = set(seeds[: len(seeds) // 2])
                held = set(seeds) - chosen
            else:
                chosen = set(seeds) & sel_set
                held = set(seeds) & rep_set if rep_set is not None else set(seeds) - sel_set
            if chosen & held:  # cannot happen with the rules above; a guard against future edits
                raise ConfigError(f"{where(task, label, a)}: seeds {seeds_text(chosen & held)} would both "
                                  "select and report.")
            for name, got in (("selection", chosen), ("report", held)):
                if not got:
                    raise ConfigError(
                        f"{where(task, label, a)} has seeds {seeds_text(seeds)}, none of them in the "
                        f"{name} set ({split}) Choose --select-seeds/--report-seeds so that every alpha has seeds "
                        "in both."
                    )
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
    dip_cells: list[DipCell] = dataclasses.field(default_factory=list)
    dips: list[Dip] = dataclasses.field(default_factory=list)
    no_dip: list[Skipped] = dataclasses.field(default_factory=list)  # finished runs without a dip
    selection: AlphaSelection | None = None  # None when held-out selection was impossible (see notes)

    def summary_text(self) -> str:
        lines = [f"botorl report: {len(self.runs)} finished runs, {len(self.skipped)} skipped -> {self.out}"]
        for s in self.skipped:
            lines.append(f"  skipped {s.path}: {s.reason}")
        for s in self.no_dip:
            lines.append(f"  no dip for {s.path}: {s.reason}")
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
    dip_window: float = DIP_WINDOW,
    select_seeds: Sequence[int] | None = None,
    report_seeds: Sequence[int] | None = None,
) -> ReportResult:
    if not (isinstance(dip_window, (int, float)) and math.isfinite(dip_window) and dip_window > 0):
        raise ConfigError(f"--dip-window must be a positive number of online env steps, got {dip_window!r}.")
    runs, skipped = find_runs(dirs)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files: list[Path] = []
    notes: list[str] = []
    dips, no_dip = dips_of(runs, dip_window)
    dip_cells = dip_table(dips, n_boot=n_boot, confidence=confidence, seed=seed)
    short = sorted({d.run.path for d in dips if d.run.steps[-1] < dip_window})
    if short:
        notes.append(
            f"{len(short)} run(s) end before the {dip_window:g}-step dip window (their dip covers only the steps "
            f"they evaluated): {', '.join(str(x) for x in short[:5])}{' ...' if len(short) > 5 else ''}"
        )
    cells = table1(runs, n_boot=n_boot, confidence=confidence, seed=seed, dips=dip_cells)
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
    atomic_write_text(out / "dip_runs.csv", dip_runs_csv(dips))
    files += [out / "table1.csv", out / "aggregate_iqm.csv", out / "dip_runs.csv"]
    if runs:
        figure5(runs, out / "figure5.png", grid_points=grid_points)
        files.append(out / "figure5.png")
        if dip_cells:
            dip_figure(dip_cells, out / "dip.png", window=dip_window, confidence=confidence)
            files.append(out / "dip.png")
        else:
            notes.append("no run has a dip (see the reasons): no dip figure")
        alpha_rows = alpha_table(runs, dip_window)
        if alpha_figure(alpha_rows, out / "alpha_sensitivity.png", window=dip_window):
            atomic_write_text(out / "alpha_sensitivity.csv", alpha_csv(alpha_rows))
            files += [out / "alpha_sensitivity.png", out / "alpha_sensitivity.csv"]
        else:
            notes.append("no alpha sweep among the runs (boto with >= 2 alphas on a task): no alpha figure")
    else:
        notes.append("no finished runs: no figures")
    selection: AlphaSelection | None
    try:
        selection = select_alpha(runs, select_seeds=select_seeds, report_seeds=report_seeds,
                                 n_boot=n_boot, confidence=confidence, seed=seed)
    except BotorlError as err:
        selection = None
        notes.append(f"no held-out alpha selection: {err}")
    pct = f"{100 * confidence:g}%"
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
        f"## Interquartile mean with {pct} stratified-bootstrap CI",
        "",
        f"IQM and percentile bootstrap ({n_boot} resamples of runs within each task, seed {seed}) "
        "after Agarwal et al. 2021 (rliable). Rows in bold aggregate all tasks of a method.",
        "",
        iqm_markdown(cells, aggs, confidence),
        "",
        f"## The dip (first {dip_window:g} online env steps)",
        "",
        f"Per run: the lowest success over every evaluation with 0 <= env_step <= {dip_window:g} (warm-up "
        "evaluations and step 0 included) minus the success at env_step 0; 0 = no drop, -1 = from always to "
        f"never solved. Per method: mean ± s.e., the {pct} percentile-bootstrap CI of the mean ({n_boot} "
        f"resamples of the runs, seed {seed}) and the IQM with its CI. Per-run values: `dip_runs.csv`; the "
        "group values are also the `dip_*` columns of `table1.csv`.",
        "",
        dip_markdown(dip_cells, dip_window, confidence) if dip_cells else "No run has a dip.",
        "",
    ]
    if no_dip:
        md += ["Finished runs without a dip:", ""] + [f"- `{s.path}`: {s.reason}" for s in no_dip] + [""]
    if (out / "dip.png") in files:
        md += ["![the dip](dip.png)", ""]
    if (out / "figure5.png") in files:
        md += ["## Figure 5", "", "![figure 5](figure5.png)", ""]
    if (out / "alpha_sensitivity.png") in files:
        md += ["## Alpha sensitivity", "", "Per alpha, mean ± s.e. over seeds (`alpha_sensitivity.csv`): success at "
               "0, 10k and final, and the dip.", "", "![alpha sensitivity](alpha_sensitivity.png)", ""]
        if selection is not None:
            md += ["Selected alpha, held out (`botorl report --select-alpha`):", "", "```", selection.text(), "```", ""]
    if skipped:
        md += ["## Skipped run directories", ""]
        md += [f"- `{s.path}`: {s.reason}" for s in skipped]
        md.append("")
    if notes:
        md += ["## Notes", ""] + [f"- {n}" for n in notes] + [""]
    atomic_write_text(out / "report.md", "\n".join(md))
    files.insert(0, out / "report.md")
    if selection is not None and selection.choices:
        atomic_write_text(out / "alpha_selection.txt", selection.text() + "\n")
        files.append(out / "alpha_selection.txt")
    # outputs of an earlier report into the same folder that this one does not replace would
    # read as this report's
    for stale in ("alpha_selection.txt", "dip.png", "alpha_sensitivity.png", "alpha_sensitivity.csv", "figure5.png"):
        if (out / stale) not in files:
            (out / stale).unlink(missing_ok=True)
    return ReportResult(out, runs, skipped, cells, aggs, files, notes, dip_cells, dips, no_dip, selection)

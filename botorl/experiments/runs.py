"""Run directories as the report reads them: only status "finished" counts, every other one
found is skipped with the reason. A run directory is data from anywhere: its files are read
only when they are regular files of a bounded size (botorl.io.read_bounded)."""

from __future__ import annotations

import dataclasses
import io
import json
import math
import os
from collections import defaultdict
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from botorl.errors import BotorlError
from botorl.configs.methods import METHODS
from botorl.configs.schema import flatten
from botorl.envs.metric import Metric
from botorl.envs.metric import of_config as metric_of_config
from botorl.io import CSV_LIMIT, csv_rows, read_bounded, read_json_bounded, read_json_object


@dataclasses.dataclass
class Run:
    path: Path
    task: str
    method: str
    pretrain: str | None
    alpha: float | None
    seed: int | None
    # the task's headline metric (``metric``: success where the task defines it, else the return
    # or the normalised score), under the names of the goal tasks the report was written for
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
    pretrain_sha256: str | None = None  # the pre-trained agent it starts from (summary.json); pairs match on it
    metric: Metric = Metric()  # what success_* and success hold (botorl/envs/metric.py)

    @property
    def label(self) -> str:
        base = f"boto+{self.pretrain}" if self.method == "boto" and self.pretrain else self.method
        return f"{base} [{self.variant}]" if self.variant else base

    @property
    def key(self) -> tuple[str, str, float | None]:
        return (self.task, self.label, self.alpha if self.method == "boto" else None)


@dataclasses.dataclass
class Skipped:
    path: Path
    reason: str


def to_float(v: Any) -> float:
    """``v`` as a float; nan for what is no number (a field cut short, edited or missing)."""
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def relative(path: Path | str, base: Path | str | None) -> str:
    """``path`` relative to ``base`` (the report's folder; links not resolved), so committed
    reports hold no path of the machine that made them; ``path`` itself when ``base`` is None."""
    return str(path) if base is None else os.path.relpath(os.path.abspath(path), os.path.abspath(base))


def read_eval_csv(path: Path, metric: Metric = Metric()) -> tuple[np.ndarray, np.ndarray]:
    """(env_step, the metric: success by default), one value per step: the last row written for
    it (several stages evaluate at env_step 0; the last is what fine-tuning starts from)."""
    col = metric.column
    with io.StringIO(read_bounded(path, CSV_LIMIT), newline="") as f:
        header, rows = csv_rows(f, path.name)
    if header is None or not {"env_step", col} <= set(header):
        raise ValueError(f"{path.name} has no env_step/{col} columns (header {header})")
    by_step: dict[float, float] = {}
    for row in rows:
        step, value = to_float(row.get("env_step")), metric.of(to_float(row.get("success")), to_float(row.get("return")))
        if math.isfinite(step) and step >= 0 and math.isfinite(value):
            by_step[step] = value
    steps = np.asarray(sorted(by_step), dtype=np.float64)
    return steps, np.asarray([by_step[s] for s in steps], dtype=np.float64)


# Config fields that differ between runs of one method without making them another method:
# the member's identity (seed, alpha and their copies), where and how it logs, how updates are
# chunked into calls, where its pre-training came from (the same numbers either way), and the
# folder a task of one's own was imported from.
_SAME_METHOD = {"seed", "alpha", "out", "pretrained", "progress", "tensorboard", "wandb", "checkpoint_every",
                "boto.alpha", "boto.seed", "eval.num_envs", "offline.updates_per_call", "boto.steps_per_call",
                "offline.sample_on_device", "env.path"}


def _settings(config: dict) -> dict[str, Any]:
    # environment.*: what the run was made with (pipeline/provenance.py), not a setting;
    # metric.*: recorded from the task, the same for every run of it (runs made before the
    # record have none, and are the same method)
    return {k: json.dumps(v, sort_keys=True) for k, v in flatten(config).items()
            if k not in _SAME_METHOD and not k.endswith("log_every") and not k.startswith(("environment.", "metric."))}


def label_variants(runs: list[Run]) -> None:
    """Runs of one method on one task that differ in a setting (``--boto.train-actor``, another
    ``online.steps``) are different variants, not more seeds of one: each gets the settings in
    which its method's runs differ (on any task) appended to its label, e.g.
    ``boto+calql [boto.train_actor=true]``, so tables, curves and dips keep them apart."""
    for group in group_by(runs, lambda r: (r.method, r.pretrain or "")).values():
        varying: set[str] = set()
        for same_task in group_by(group, lambda r: r.task).values():
            keys = set().union(*(r.settings for r in same_task))
            varying |= {k for k in keys if len({r.settings.get(k) for r in same_task}) > 1}
        for r in group:
            r.variant = ", ".join(f"{k}={r.settings.get(k, 'null')}" for k in sorted(varying))


def _load_run(run_dir: Path) -> Run | Skipped:
    try:
        summary = read_json_bounded(run_dir / "summary.json")
        if not isinstance(summary, dict):
            raise ValueError("not a JSON object")
    except (OSError, ValueError) as err:
        return Skipped(run_dir, f"summary.json unreadable ({err})")
    status = summary.get("status")
    if status != "finished":
        error = f" ({summary['error']})" if summary.get("error") else ""
        return Skipped(run_dir, f"status is {status!r}, not 'finished'{error}")
    config = read_json_object(run_dir / "config.json") or {}

    def field(name: str) -> Any:
        return summary[name] if summary.get(name) is not None else config.get(name)

    if not field("task") or not field("method"):
        return Skipped(run_dir, "summary.json and config.json name no task/method")
    eval_path = run_dir / "eval.csv"
    if not eval_path.exists():
        return Skipped(run_dir, "finished but eval.csv is missing")
    metric = metric_of_config(config)
    try:
        steps, success = read_eval_csv(eval_path, metric)
    except (OSError, ValueError) as err:
        return Skipped(run_dir, f"eval.csv unreadable ({err})")
    points = {p: to_float(summary.get(f"{metric.name}_{p}")) for p in ("initial", "10k", "final")}
    if f"{metric.name}_initial" not in summary:  # a summary from before the metric's fields: its eval.csv
        points = _points_of(steps, success)
    alpha = field("alpha")
    seed = field("seed")
    if seed is not None and not (isinstance(seed, int) and not isinstance(seed, bool)):
        return Skipped(run_dir, f"its seed {str(seed)[:40]!r} is not an integer")
    if not isinstance(field("task"), str) or not isinstance(field("method"), str):
        return Skipped(run_dir, "summary.json and config.json name no task/method as text")
    return Run(
        path=run_dir,
        task=str(field("task")),
        method=str(field("method")),
        pretrain=None if field("pretrain") in (None, "") else str(field("pretrain")),
        alpha=None if alpha is None or not math.isfinite(to_float(alpha)) else round(float(alpha), 6),
        seed=None if seed is None else int(seed),
        success_initial=points["initial"],
        success_10k=points["10k"],
        success_final=points["final"],
        steps=steps,
        success=success,
        settings=_settings(config),
        dense_from=_dense_from(config),
        config=config,
        pretrain_sha256=sha if isinstance(sha := summary.get("pretrain_sha256"), str) and len(sha) == 64 else None,
        metric=metric,
    )


def _points_of(steps: np.ndarray, values: np.ndarray) -> dict[str, float]:
    """The summary's three points (pipeline/summary.py) from the curve: step 0, the first
    evaluation at or after 10k, the last."""
    at0, after = values[steps == 0], values[steps >= 10_000]
    return {"initial": float(at0[-1]) if at0.size else math.nan, "10k": float(after[0]) if after.size else math.nan,
            "final": float(values[-1]) if values.size else math.nan}


def _dense_from(config: dict) -> float | None:
    ev, wu = config.get("eval"), config.get("warmup")
    if not isinstance(ev, dict) or not isinstance(wu, dict) or not to_float(ev.get("dense_interval")) > 0:
        return None
    start = to_float(wu.get("steps"))
    return start if math.isfinite(start) and start >= 0 else None


def _last_line(path: Path) -> str:
    try:
        lines = [ln.strip() for ln in read_bounded(path, 4096, tail=True).splitlines() if ln.strip()]
    except (OSError, ValueError):
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
            raise BotorlError(f"{top} is not a directory; give run or sweep directories.")
        for root, subdirs, files in os.walk(top):
            is_run = "summary.json" in files or ("config.json" in files and ("eval.csv" in files or "checkpoints" in subdirs))
            if not is_run and "population.json" in files:  # a population: its members are run directories
                subdirs[:] = sorted(d for d in subdirs if not d.startswith(".") and d != "checkpoints")
                continue
            if not is_run and "sweep-trial.log" not in files:  # a folder of runs: searched further down
                subdirs[:] = sorted(d for d in subdirs if not d.startswith("."))
                continue
            subdirs[:] = []  # a run, or a sweep trial whose `botorl run` failed before starting
            here = Path(root)
            if (resolved := here.resolve()) in seen:  # reached again through overlapping folders: read once
                continue
            seen.add(resolved)
            if "summary.json" in files:
                loaded = _load_run(here)
            elif is_run:
                loaded = Skipped(here, "no summary.json (the run never got far enough to write one)")
            else:
                loaded = Skipped(here, f"the run never started; sweep-trial.log ends: {_last_line(here / 'sweep-trial.log')}")
            (runs if isinstance(loaded, Run) else skipped).append(loaded)
    label_variants(runs)
    runs.sort(key=lambda r: (r.task, r.label, -99 if r.alpha is None else r.alpha, r.seed or 0))
    return runs, skipped


def group_by(items: Iterable, key) -> dict[Any, list]:
    """``items`` in lists by ``key(item)``, in the order the keys first appear."""
    groups: dict[Any, list] = defaultdict(list)
    for x in items:
        groups[key(x)].append(x)
    return dict(groups)


def from_scratch(method: str) -> bool:
    m = METHODS.get(method)
    return m is not None and not m.pretrains


def key_order(key: tuple[str, str, float | None]) -> tuple:
    return (key[0], key[1], -99 if key[2] is None else key[2])

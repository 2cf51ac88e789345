"""The headline metric of a task: what a run's summary, curve and report are about.

Success where the task defines it (every botorl task, and a task of one's own whose env's info
has its success key); else the episode return, or, when the task gives reference scores, the
normalised score ``100 * (R - ref_min_score) / (ref_max_score - ref_min_score)`` (D4RL's
convention: 0 = the reference low, e.g. a random policy, 100 = the reference high, e.g. an
expert). The run's config records it (``RunConfig.metric``); readers of a run directory go
through ``of_config`` so that runs made before the record still read as what they were.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

from botorl.errors import ConfigError

NAMES = ("success", "return", "score")


@dataclass(frozen=True)
class Metric:
    name: str = "success"  # one of NAMES
    ref_min_score: float | None = None
    ref_max_score: float | None = None

    @property
    def column(self) -> str:
        """The eval.csv column it is computed from."""
        return "success" if self.name == "success" else "return"

    @property
    def label(self) -> str:
        """In words, for tables and axes."""
        return {"success": "success", "return": "return", "score": "normalised score"}[self.name]

    @property
    def bounded(self) -> bool:
        """Success rates lie in [0, 1], so their axes and the dip's are fixed; returns have no scale."""
        return self.name == "success"

    def of(self, success: float, episode_return: float) -> float:
        """The metric of one evaluation, from its success rate and mean episode return."""
        if self.name == "success":
            return success
        if self.name == "score":
            return normalised_score(episode_return, self.ref_min_score, self.ref_max_score)
        return episode_return

    def describe(self) -> str:
        """One line saying which metric, for report.md and the printed summary."""
        if self.name == "success":
            return "success rate (the task defines success)"
        if self.name == "score":
            return (f"normalised score, 100 * (return - ref_min) / (ref_max - ref_min) with the task's reference "
                    f"scores ref_min {self.ref_min_score:g}, ref_max {self.ref_max_score:g} (the task has no success)")
        return "episode return, undiscounted and in the env's own reward units (the task has no success)"


def normalised_score(episode_return: float, ref_min: float | None, ref_max: float | None) -> float:
    if ref_min is None or ref_max is None:
        return math.nan
    return 100.0 * (episode_return - ref_min) / (ref_max - ref_min)


def check_refs(ref_min: Any, ref_max: Any, where: str) -> tuple[float | None, float | None]:
    """(ref_min, ref_max) as floats, both or neither, finite, min < max; ConfigError otherwise."""
    if ref_min is None and ref_max is None:
        return None, None
    flags = "ref_min_score and ref_max_score (--ref-min-score, --ref-max-score)"
    if ref_min is None or ref_max is None:
        raise ConfigError(f"{where}: give both {flags} or neither; the normalised score needs both ends.")
    if any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v))
           for v in (ref_min, ref_max)):
        raise ConfigError(f"{where}: {flags} must be finite numbers, got {ref_min!r} and {ref_max!r}.")
    lo, hi = float(ref_min), float(ref_max)
    if not lo < hi:
        raise ConfigError(f"{where}: ref_min_score {lo:g} must be below ref_max_score {hi:g} (the "
                          f"return of a poor policy, e.g. random, and of a good one, e.g. an expert).")
    return lo, hi


def of_task(spec) -> Metric:
    """A task's headline metric: success where it defines it, else (normalised) return."""
    user = getattr(spec, "user", None)
    if user is None or user.success_key is not None:
        return Metric("success")
    lo, hi = getattr(spec, "ref_min_score", None), getattr(spec, "ref_max_score", None)
    return Metric("score", lo, hi) if lo is not None and hi is not None else Metric("return")


def of_config(config: Mapping[str, Any] | Any) -> Metric:
    """The metric a run's config (a RunConfig, or config.json as read: hostile data) records; a
    config from before the record is success, or return where it says success was off."""
    get = (lambda d, k: d.get(k) if isinstance(d, Mapping) else getattr(d, k, None))
    rec = get(config, "metric")
    name = get(rec, "name")
    if name in NAMES:
        lo, hi = get(rec, "ref_min_score"), get(rec, "ref_max_score")
        if name == "score":
            try:
                lo, hi = check_refs(lo, hi, "the run's config.json")
            except ConfigError:
                return Metric("return")  # a damaged record: the raw return is still right
            return Metric("score", lo, hi)
        return Metric(name)
    env = get(config, "env")
    return Metric("return") if env is not None and get(env, "success_off") else Metric("success")


def headline_of_summary(summary: Mapping[str, Any]) -> str:
    """The metric a summary.json is about: the one whose ``_initial`` it carries (success first,
    as a goal task's summary also carries the return)."""
    return next((name for name in ("success", "score", "return") if f"{name}_initial" in summary), "success")


def episode_success(prev: float, success, mode: str) -> float:
    """An episode's success after a step whose ``info["success"]`` is ``success``: "any" mode the
    maximum so far, "last" this step's (kitchen's). The one rule for every loop that steps envs."""
    return max(prev, float(success)) if mode == "any" else float(success)

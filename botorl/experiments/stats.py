"""Statistics of the report and the number formats its files share.

Mean +- SE over seeds with SE = sample std (ddof=1) / sqrt(n), as the paper's Table 1 reports
them; the interquartile mean (IQM) with a percentile stratified-bootstrap CI after Agarwal et
al. 2021 (rliable; written from its description, no rliable code): cut floor(n/4) scores from
each end, resample runs with replacement within each task; paired statistics for pairs.py.
"""

from __future__ import annotations

import csv
import io
import math
import textwrap
from typing import Any, Iterable, Sequence

import numpy as np
from scipy import stats

from botorl.errors import ConfigError
from botorl.io import atomic_save_figure, pyplot


def mean_se(values: Sequence[float]) -> tuple[float, float, int]:
    """Mean and standard error (ddof=1) of the finite values; SE is nan for n < 2."""
    x = np.asarray([v for v in values if v is not None and math.isfinite(v)], dtype=np.float64)
    n = int(x.size)
    if n == 0:
        return math.nan, math.nan, 0
    se = float(x.std(ddof=1) / math.sqrt(n)) if n >= 2 else math.nan
    return float(x.mean()), se, n


def iqm(values: Sequence[float] | np.ndarray, axis: int = -1) -> Any:
    """Interquartile mean: drop floor(n/4) scores from each end, average the rest."""
    x = np.sort(np.asarray(values, dtype=np.float64), axis=axis)
    n = x.shape[axis]
    if n == 0:
        return math.nan
    cut = int(0.25 * n)
    out = np.take(x, np.arange(cut, n - cut), axis=axis).mean(axis=axis)
    return float(out) if np.ndim(out) == 0 else out


def stratified_bootstrap_iqm(scores_per_task: Sequence[Sequence[float]], *, n_boot: int = 2000,
                             confidence: float = 0.95, seed: int = 0) -> tuple[float, float, float]:
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


def seed_stats(values: Sequence[float], *, n_boot: int, confidence: float, seed: int) -> dict[str, float]:
    """Mean, s.e., n and the IQM with its bootstrap CI of one group's runs."""
    mean, se, n = mean_se(values)
    point, lo, hi = stratified_bootstrap_iqm([values], n_boot=n_boot, confidence=confidence, seed=seed)
    return {"mean": mean, "se": se, "n": n, "iqm": point, "iqm_lo": lo, "iqm_hi": hi}


def bootstrap_mean_ci(
    values: Sequence[float], *, n_boot: int = 2000, confidence: float = 0.95, seed: int = 0
) -> tuple[float, float]:
    """Percentile bootstrap CI of the mean over ``n_boot`` resamples of the runs; (nan, nan) for
    fewer than 2 finite values (one run says nothing about its spread)."""
    x = np.asarray([v for v in values if v is not None and math.isfinite(v)], dtype=np.float64)
    if x.size < 2 or n_boot <= 0:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    boot = x[rng.integers(0, x.size, size=(n_boot, x.size))].mean(axis=1)
    lo, hi = np.quantile(boot, [(1 - confidence) / 2, 1 - (1 - confidence) / 2])
    return float(lo), float(hi)


EQUAL = 1e-9  # differences within this are ties


def t_interval(values: Sequence[float], confidence: float = 0.95) -> tuple[float, float]:
    """mean +- t_{(1+c)/2, n-1} * s.e.; (nan, nan) for n < 2."""
    mean, se, n = mean_se(values)
    if n < 2:
        return math.nan, math.nan
    half = float(stats.t.ppf((1 + confidence) / 2, n - 1)) * se
    return mean - half, mean + half


def wilcoxon_p(values: Sequence[float]) -> float:
    """Two-sided Wilcoxon signed-rank p-value; zero differences dropped; nan if none is left."""
    d = np.asarray([v for v in values if math.isfinite(v) and abs(v) > EQUAL], dtype=np.float64)
    if d.size == 0:
        return math.nan
    return float(stats.wilcoxon(d, zero_method="wilcox", alternative="two-sided").pvalue)


def csv_text(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    w.writerows(rows)
    return buf.getvalue()


def md_table(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> str:
    """A markdown table: the header, its rule, one line a row."""
    lines = ["| " + " | ".join(map(str, cells)) + " |" for cells in [header, *rows]]
    return "\n".join([lines[0], "|" + "---|" * len(header), *lines[1:]])


def fmt_float(x: float) -> str:
    return "" if x is None or (isinstance(x, float) and not math.isfinite(x)) else repr(float(x))


def fmt_mean_se(st: dict[str, float], sign: str = "") -> str:
    """Mean ± s.e. to 2 places; "(n=1)" where one run has no s.e.; "-" without runs."""
    if st["n"] == 0:
        return "-"
    if not math.isfinite(st["se"]):
        return f"{st['mean']:{sign}.2f} (n=1)"
    return f"{st['mean']:{sign}.2f} ± {st['se']:.2f}"


def fmt_iqm(st: dict[str, float], sign: str = "") -> str:
    """The IQM and its CI to 2 places; the IQM alone where there is no CI; "-" without runs."""
    if not math.isfinite(st["iqm"]):
        return "-"
    if not math.isfinite(st["iqm_lo"]):
        return f"{st['iqm']:{sign}.2f}"
    return f"{st['iqm']:{sign}.2f} [{st['iqm_lo']:{sign}.2f}, {st['iqm_hi']:{sign}.2f}]"


def alpha_text(alpha: float | None) -> str:
    return "" if alpha is None else f"{alpha:+.2f}"


def panels(n: int, width: float, height: float, ncols: int | None = None, **subplots: Any):
    """(fig, axes): ``n`` panels of ``width`` x ``height`` inches, ``ncols`` (default up to 3) a
    row, the spare ones hidden."""
    ncols = ncols or min(3, max(1, n))
    nrows = math.ceil(n / ncols)
    fig, axes = pyplot().subplots(nrows, ncols, figsize=(width * ncols, height * nrows), squeeze=False, **subplots)
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    return fig, axes


def label_colors(labels: Iterable[str]) -> dict:
    return {lab: pyplot().cm.tab10(i % 10) for i, lab in enumerate(sorted(set(labels)))}


def save_figure(fig, path, title: str, **savefig: Any) -> None:
    """The figure with its title wrapped to its width, written atomically and closed."""
    chars = max(20, int(fig.get_figwidth() * 11))  # ~11 characters an inch at 10 pt
    fig.suptitle("\n".join(textwrap.wrap(title, chars)), fontsize=10)
    fig.tight_layout()
    atomic_save_figure(fig, path, **savefig)
    pyplot().close(fig)


def line_label(label: str, alpha: float | None, multi_alpha: bool) -> str:
    return f"{label} α={alpha_text(alpha) or 'preset'}" if multi_alpha else label


MAX_RESAMPLES = 1_000_000  # 2,000 is the default; more than a million says nothing new and takes hours


def check_bootstrap(n_boot, confidence) -> None:
    """ConfigError unless 1 <= resamples <= MAX_RESAMPLES and 0 < confidence < 1."""
    if isinstance(n_boot, bool) or not isinstance(n_boot, int) or not 1 <= n_boot <= MAX_RESAMPLES:
        raise ConfigError(f"--bootstrap {n_boot!r}: give a whole number of resamples from 1 to {MAX_RESAMPLES:,} "
                          "(2000 is the default).")
    if not isinstance(confidence, (int, float)) or not 0.0 < float(confidence) < 1.0:
        raise ConfigError(f"--confidence {confidence!r}: give a level strictly between 0 and 1, e.g. 0.95.")


def fmt_ci(lo: float, hi: float, digits: int = 2) -> str:
    """A confidence interval as ``[lo, hi]`` with signs, or "-" when there is none."""
    return "-" if not math.isfinite(lo) else f"[{lo:+.{digits}f}, {hi:+.{digits}f}]"

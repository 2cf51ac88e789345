"""Statistics of the report and the number formats its files share.

Mean +- SE over seeds with SE = sample std (ddof=1) / sqrt(n), as the paper's Table 1 reports
them; the interquartile mean (IQM) with a percentile stratified-bootstrap CI after Agarwal et
al. 2021 (rliable; written from its description, no rliable code): cut floor(n/4) scores from
each end, resample runs with replacement within each task; paired statistics for pairs.py.
"""

from __future__ import annotations

import math
import textwrap
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
from scipy import stats

from botorl.errors import ConfigError
from botorl.io import atomic_save_figure, csv_text, pyplot  # csv_text: the report's modules take it from here


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


ZERO = 1e-9  # |d| <= ZERO counts as a zero ("equal") difference, and |d|s this close as tied


def t_interval(values: Sequence[float], confidence: float = 0.95) -> tuple[float, float]:
    """mean +- t_{(1+c)/2, n-1} * s.e.; (nan, nan) for n < 2."""
    mean, se, n = mean_se(values)
    if n < 2:
        return math.nan, math.nan
    half = float(stats.t.ppf((1 + confidence) / 2, n - 1)) * se
    return mean - half, mean + half


def _abs_ranks(a: np.ndarray) -> tuple[np.ndarray, list[int]]:
    """Average ranks of ``a`` (1 = smallest) and the sizes of its tie groups; values within
    ZERO of their neighbour tie, so that 0.7 - 0.4 and 0.3 are one value, not two."""
    order = np.argsort(a, kind="stable")
    ranks, sizes = np.empty(a.size, np.float64), []
    start = 0
    for i in range(1, a.size + 1):
        if i == a.size or a[order[i]] - a[order[i - 1]] > ZERO:
            ranks[order[start:i]] = (start + 1 + i) / 2  # the mean of ranks start+1 .. i
            sizes.append(i - start)
            start = i
    return ranks, sizes


def _subset_sum_counts(n: int) -> np.ndarray:
    """counts[w] = how many subsets of {1, ..., n} sum to w: W+'s null distribution times 2^n
    (dynamic programming; int64 is exact, 2^50 fits)."""
    counts = np.zeros(n * (n + 1) // 2 + 1, np.int64)
    counts[0] = 1
    for k in range(1, n + 1):
        counts[k:] = counts[k:] + counts[:-k]  # the right side is evaluated before the write
    return counts


EXACT_MAX_N = 50  # the plan's limit for the exact test


def wilcoxon_signed_rank(d: Sequence[float]) -> tuple[float, str]:
    """Two-sided Wilcoxon signed-rank p, and the method used, as a plan states it: zeros
    (|d| <= ZERO) and non-finite values dropped; 'exact' (the null distribution of W+, the rank
    sum of the positive d, counted by dynamic programming) when no |d| ties and n <= 50, else
    'normal': z = (W+ - n(n+1)/4) / sqrt(n(n+1)(2n+1)/24 - sum(t^3 - t)/48) over tie groups of
    size t, no continuity correction. (nan, 'none') when no difference is left. botorl's own
    code, so the p does not change with the installed SciPy (scipy.stats.wilcoxon's default
    method has changed between versions)."""
    x = np.asarray([v for v in d if v is not None and math.isfinite(v) and abs(v) > ZERO], dtype=np.float64)
    n = int(x.size)
    if n == 0:
        return math.nan, "none"
    ranks, ties = _abs_ranks(np.abs(x))
    w_plus = float(ranks[x > 0].sum())
    if max(ties) == 1 and n <= EXACT_MAX_N:
        counts = _subset_sum_counts(n)
        w = int(round(w_plus))
        total = float(2**n)
        below, above = counts[: w + 1].sum() / total, counts[w:].sum() / total
        return float(min(1.0, 2 * min(below, above))), "exact"
    mean = n * (n + 1) / 4
    var = n * (n + 1) * (2 * n + 1) / 24 - sum(t**3 - t for t in ties) / 48
    z = (w_plus - mean) / math.sqrt(var)
    return float(min(1.0, 2 * stats.norm.sf(abs(z)))), "normal"


def holm(pvalues: Sequence[float]) -> list[float]:
    """Holm's step-down adjusted p-values over all the tests given: sorted ascending, the k-th is
    max over j <= k of min(1, (m - j + 1) p_(j)). A test without data (p nan) stays nan but
    still counts in m, as a plan that names it fixes the family (conservative)."""
    idx = [i for i, p in enumerate(pvalues) if math.isfinite(p)]
    order = sorted(idx, key=lambda i: pvalues[i])
    m, out, running = len(pvalues), [math.nan] * len(pvalues), 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * pvalues[i]))
        out[i] = running
    return out


def block_range(values: Sequence[float], blocks: Sequence[str]) -> tuple[float, float, list[tuple[str, float]]]:
    """The smallest and largest block mean, and each block's mean (sorted by block name); nan,
    nan, [] without values. Reported as the "range of block means", never as a CI: with B
    blocks a whole-block bootstrap draws "all one block" with probability B^-B per block
    (1/27 for 3), so below ~10 blocks its 95% interval is just this range."""
    by_block: dict[str, list[float]] = {}
    for v, b in zip(values, blocks, strict=True):
        if v is not None and math.isfinite(v):
            by_block.setdefault(str(b), []).append(float(v))
    means = [(b, float(np.mean(by_block[b]))) for b in sorted(by_block)]
    if not means:
        return math.nan, math.nan, []
    return min(m for _, m in means), max(m for _, m in means), means


def tost(d: Sequence[float], margin: float, alpha: float = 0.05) -> dict[str, Any]:
    """Two one-sided t-tests of the mean paired difference against the margin +-``margin``:
    {'ci90': the (1 - 2 alpha) t-interval, 'margin', 'p': the larger one-sided p,
    'verdict': 'equivalent' (that interval inside [-margin, +margin]), 'different' (else, when
    the (1 - alpha) t-interval excludes 0) or 'undecided'}. Fewer than 2 values: nan, undecided."""
    mean, se, n = mean_se(d)
    ci = t_interval(d, 1 - 2 * alpha)
    out = {"ci90": ci, "margin": margin, "p": math.nan, "verdict": "undecided"}
    if n < 2:
        return out
    if se > 0:
        lower = float(stats.t.sf((mean + margin) / se, n - 1))  # H0: mean <= -margin
        upper = float(stats.t.cdf((mean - margin) / se, n - 1))  # H0: mean >= +margin
        out["p"] = max(lower, upper)
    else:  # all differences equal: no spread, the mean is known
        out["p"] = 0.0 if abs(mean) < margin else 1.0
    lo95, hi95 = t_interval(d, 1 - alpha)
    if -margin <= ci[0] and ci[1] <= margin:
        out["verdict"] = "equivalent"
    elif lo95 > 0 or hi95 < 0:
        out["verdict"] = "different"
    return out


def detectable_effect(sd: float, n: int, power: float = 0.8, alpha: float = 0.05) -> float:
    """The smallest paired mean difference a two-sided level-``alpha`` test detects with
    probability ``power`` from n pairs of per-pair SD ``sd``: (z_{1-alpha/2} + z_power) sd / sqrt(n)
    (normal approximation; 2.80 sd / sqrt(n) at the defaults); nan for n < 2."""
    if n < 2 or not math.isfinite(sd):
        return math.nan
    z = float(stats.norm.ppf(1 - alpha / 2)) + float(stats.norm.ppf(power))
    return z * sd / math.sqrt(n)


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


def save_figure(fig, path, title: str, **savefig: Any) -> Path:
    """The figure with its title wrapped to its width, written atomically (and closed); its path."""
    chars = max(20, int(fig.get_figwidth() * 11))  # ~11 characters an inch at 10 pt
    fig.suptitle("\n".join(textwrap.wrap(title, chars)), fontsize=10)
    fig.tight_layout()
    return atomic_save_figure(fig, path, **savefig)


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

"""`botorl study report`: a study's analysis from its records alone, no run directory needed.

Every run's endpoints come from the records `botorl study run` copied (``<results>/<block>/<arm>/
<task>/seed<k>/``), or, for a legacy block, from the ``paired.csv`` its `botorl report` wrote:
each row's run is matched to the arm whose resolved config gives its label and alpha. Arms pair
within a block, per task and seed: one pre-training (`study run` checked the digests). Per
comparison and endpoint the report shows what docs/running.md, "Writing a study", lists; the
statistics are stats.py's.
"""

from __future__ import annotations

import json
import math
import os
import shlex
from collections import Counter
from pathlib import Path

import numpy as np

from botorl.configs.schema import flatten, to_dict
from botorl.errors import ConfigError
from botorl.experiments.dip import run_dip
from botorl.experiments.manipulation import q_around_boto
from botorl.experiments.pairs import canonical_label, read_pairs_csv
from botorl.experiments.report import make_report
from botorl.experiments.runs import Run, find_runs
from botorl.experiments.stats import (
    ZERO,
    block_range,
    bootstrap_mean_ci,
    csv_text,
    detectable_effect,
    fmt_ci,
    fmt_float,
    holm,
    md_table,
    pyplot,
    save_figure,
    t_interval,
    tost,
    wilcoxon_signed_rank,
)
from botorl.experiments.study import ENDPOINTS, STATE, Block, Study, arm_config, seeds_text
from botorl.io import atomic_write_text, read_json_object

Key = tuple[str, str, str, int]  # (block, arm, task, seed)
MANIPULATION = ("q_data_change", "q_uniform_change")  # compared between arms like an endpoint
NAMES = {"dip": "dip", "success_10k": "success at 10k", "window_mean": "mean success in the window",
         "success_0": "success at 0", "lowest": "lowest in the window", "success_final": "final success",
         "q_data_change": "Q change, dataset actions", "q_uniform_change": "Q change, uniform actions"}


def endpoints_of(run: Run, window_end: float) -> dict[str, float]:
    """A run's endpoints (study.ENDPOINTS): the dip and its parts over the window, the window's
    mean success (evaluations from the warm-up's end to ``window_end``), success at 10k and at the end."""
    d = run_dip(run, window_end)
    if isinstance(d, str):
        out = dict.fromkeys(("dip", "success_0", "lowest"), math.nan)
    else:
        out = {"dip": d.value, "success_0": d.initial, "lowest": d.lowest}
    start = run.dense_from if run.dense_from is not None else 0.0
    inside = (run.steps >= start) & (run.steps <= window_end) & (run.steps > 0)
    out["window_mean"] = float(run.success[inside].mean()) if inside.any() else math.nan
    return out | {"success_10k": run.success_10k, "success_final": run.success_final}


class Records:
    """Every run's values by (block, arm, task, seed), and what the records say of their making."""

    def __init__(self, study: Study):
        self.study = study
        self.values: dict[Key, dict[str, float]] = {}
        self.digests: dict[Key, str] = {}  # the pre-trained agent each recorded run starts from
        self.unpaired: set[tuple[Key, Key]] = set()  # same block, task and seed, yet two pre-trainings
        self.commits: Counter = Counter()
        self.notes: list[str] = []
        for block in study.blocks:  # a legacy block's runs are the rows of its paired.csv
            (self._read_block if block.paired_csv is None else self._read_legacy)(block)

    def _read_block(self, block: Block) -> None:
        for arm in self.study.arms:
            folder = self.study.records_dir(block, arm)
            runs, skipped = find_runs([folder]) if folder.is_dir() else ([], [])
            if not runs:
                self.notes.append(f"{block.name}/{arm.key}: no records yet (`botorl study run` has not finished it)")
            for s in skipped:
                self.notes.append(f"{block.name}/{arm.key}: skipped {s.path.name} ({s.reason})")
            for r in runs:
                key = (block.name, arm.key, r.task, r.seed)
                self.values[key] = endpoints_of(r, self.study.window_end) | q_around_boto(r.path)
                if r.pretrain_sha256:
                    self.digests[key] = r.pretrain_sha256
                env = r.config.get("environment")
                self.commits[str(env.get("commit")) if isinstance(env, dict) else "not recorded"] += 1

    def _read_legacy(self, block: Block) -> None:
        try:
            pairs = read_pairs_csv(block.paired_csv)
        except (OSError, KeyError, ValueError, TypeError) as err:
            raise ConfigError(f"{self.study.path}: [[blocks]] {block.name} paired_csv {block.paired_csv}: not a "
                              f"paired.csv that `botorl report` wrote ({err}).") from None
        labels = arm_labels(self.study, [p.label for p in pairs] + [p.reference for p in pairs])
        ref = self.study.reference
        unmatched = 0
        for p in pairs:
            if p.reference != labels[ref][0]:
                raise ConfigError(f"{block.paired_csv}: a row's reference is {p.reference!r}, but the study's "
                                  f"reference arm {ref!r} runs as {labels[ref][0]!r}.")
            found = [k for k, (label, alpha) in labels.items()
                     if k != ref and label == p.label and _same_alpha(alpha, p.alpha)]
            if len(found) > 1:
                raise ConfigError(f"{block.paired_csv}: the row {p.label!r} (alpha {p.alpha}) fits arms "
                                  f"{', '.join(found)} alike; make their settings differ.")
            if not found:
                unmatched += 1
                continue
            key = (block.name, found[0], p.task, p.seed)
            if key in self.values:
                raise ConfigError(f"{block.paired_csv}: two rows for arm {found[0]} at seed {p.seed}.")
            self.values[key] = dict(p.other)
            self.values.setdefault((block.name, ref, p.task, p.seed), dict(p.ref))
        if unmatched:
            self.notes.append(f"{block.name}: {unmatched} row(s) of {block.paired_csv.name} are runs of no arm "
                              "of the study (left out)")
        self.notes.append(f"{block.name}: a legacy block, read from its {block.paired_csv.name}; it keeps no run "
                          "records, so its runs' commit and pre-training digests cannot be checked here")

    def differences(self, x: str, y: str, quantity: str) -> tuple[list[float], list[str]]:
        """x − y per (block, task, seed) that ran both from one pre-training (where the records
        name it), with each difference's block."""
        vals, blocks = [], []
        for key in sorted(self.values):
            block, arm, task, seed = key
            other = self.values.get(pair := (block, y, task, seed))
            if arm != x or other is None:
                continue
            a, b = self.digests.get(key), self.digests.get(pair)
            if a and b and a != b:  # two pre-trainings: no pair (`study run` refuses to make them)
                self.unpaired.add((key, pair))
                continue
            d = self.values[key].get(quantity, math.nan) - other.get(quantity, math.nan)
            if math.isfinite(d):
                vals.append(d)
                blocks.append(block)
        return vals, blocks

    def arm_values(self, arm: str, quantity: str) -> list[float]:
        return [v[quantity] for (_, a, _, _), v in sorted(self.values.items())
                if a == arm and math.isfinite(v.get(quantity, math.nan))]


def _same_alpha(a: float | None, b: float | None) -> bool:
    return (a is None) == (b is None) and (a is None or round(a, 6) == round(b, 6))


def arm_labels(study: Study, seen: list[str]) -> dict[str, tuple[str, float | None]]:
    """Each arm's label and alpha as `botorl report` writes them, over the variant keys the
    ``seen`` labels of its method show: the arm's own resolved config (the sweep's path) names
    the values, so a row maps to an arm by what it ran, not by a hard-coded name."""
    keys: dict[str, set[str]] = {}
    for label in seen:
        base, _, variant = label.partition(" [")
        keys.setdefault(base, set()).update(v.split("=", 1)[0] for v in variant.rstrip("]").split(", ") if v)
    out = {}
    for arm in study.arms:
        cfg = arm_config(study, arm, study.tasks[0])
        base = f"boto+{cfg.pretrain}" if cfg.method == "boto" and cfg.pretrain else cfg.method
        flat = flatten(to_dict(cfg))
        variant = ", ".join(f"{k}={json.dumps(flat.get(k), sort_keys=True)}" for k in sorted(keys.get(base, ())))
        out[arm.key] = (canonical_label(f"{base} [{variant}]" if variant else base),
                        cfg.alpha if cfg.method == "boto" else None)
    return out


# ----------------------------------------------------------------------------- the analysis

def comparison_row(rec: Records, c: tuple[str, str], quantity: str) -> dict:
    """One comparison on one quantity: everything a study's table shows of it."""
    s = rec.study
    v, blocks = rec.differences(*c, quantity)
    x = np.asarray(v, np.float64)
    sd = float(x.std(ddof=1)) if len(x) > 1 else math.nan
    lo, hi, per_block = block_range(v, blocks)
    p, method = wilcoxon_signed_rank(v)
    row = {"endpoint": quantity, "comparison": "-".join(c), "pair": c, "n": len(v),
           "mean": float(x.mean()) if len(v) else math.nan, "sd": sd,
           "boot": bootstrap_mean_ci(v, n_boot=s.n_boot, seed=s.boot_seed), "t": t_interval(v),
           "better": int((x > ZERO).sum()), "equal": int((abs(x) <= ZERO).sum()), "worse": int((x < -ZERO).sum()),
           "block_range": (lo, hi), "block_means": per_block, "p": p, "method": method, "p_holm": math.nan,
           "detectable": detectable_effect(sd, len(v)), "tost": None}
    if c in s.equivalence and quantity in ENDPOINTS:  # a margin is in the endpoints' units, not Q's
        row["tost"] = tost(v, s.equivalence[c])
    return row


def analyse(rec: Records) -> dict[str, list[dict]]:
    s = rec.study
    res = {kind: [comparison_row(rec, c, e) for e in s.endpoints for c in getattr(s, kind)]
           for kind in ("primary", "secondary", "floors")}
    for row, adj in zip(res["primary"], holm([r["p"] for r in res["primary"]])):
        row["p_holm"] = adj
    for r in res["floors"]:
        v, _ = rec.differences(*r["pair"], r["endpoint"])
        r["spread"] = tuple(np.quantile(v, [0.025, 0.975])) if v else (math.nan, math.nan)
    # did the BOTO stage move Q beyond what the other arm's did (the manipulation check)
    manipulation = [comparison_row(rec, c, q) for q in MANIPULATION for c in s.primary + s.secondary]
    return res | {"manipulation": [r for r in manipulation if r["n"]]}


# ----------------------------------------------------------------------------- writing

def _p(p: float) -> str:
    return "-" if not math.isfinite(p) else (f"{p:.3f}" if p >= 1e-3 else f"{p:.1e}")


def _num(x: float, fmt: str = "+.2f") -> str:
    return "-" if not math.isfinite(x) else f"{x:{fmt}}"


def _span(lo: float, hi: float) -> str:
    """A range that is no confidence interval, so not written like one."""
    return "-" if not math.isfinite(lo) else f"{lo:+.2f} to {hi:+.2f}"


def _tost_text(t: dict | None) -> str:
    if t is None:
        return ""
    return f"±{t['margin']:g}: {t['verdict']} (90% CI {fmt_ci(*t['ci90'])}, p {_p(t['p'])})"


def comparison_table(rows: list[dict], names: dict[str, str], holm_column: bool) -> str:
    head = ["endpoint", "comparison", "pairs", "mean difference", "95% bootstrap CI", "95% t-interval",
            "better / equal / worse", "range of block means", "Wilcoxon p (method)"]
    head += ["Holm p"] if holm_column else []
    head += ["detectable at 80% power", "equivalence (TOST)"]
    out = []
    for r in rows:
        cells = [NAMES[r["endpoint"]], " − ".join(names[k] for k in r["pair"]), r["n"], _num(r["mean"]),
                 fmt_ci(*r["boot"]), fmt_ci(*r["t"]), f"{r['better']} / {r['equal']} / {r['worse']}",
                 _span(*r["block_range"]), f"{_p(r['p'])} ({r['method']})"]
        cells += [_p(r["p_holm"])] if holm_column else []
        out.append(cells + [_num(r["detectable"], ".2f"), _tost_text(r["tost"])])
    return md_table(head, out)


def rows_csv(groups: dict[str, list[dict]]) -> str:
    head = ["kind", "endpoint", "comparison", "n", "mean", "sd", "boot_lo", "boot_hi", "t_lo", "t_hi", "better",
            "equal", "worse", "block_min", "block_max", "block_means", "wilcoxon_p", "wilcoxon_method", "holm_p",
            "detectable_80", "spread_lo", "spread_hi", "tost_margin", "tost_p", "tost_verdict"]
    out = []
    for kind, rows in groups.items():
        for r in rows:
            t = r["tost"] or {}
            out.append([kind, r["endpoint"], r["comparison"], r["n"], *map(fmt_float, (r["mean"], r["sd"], *r["boot"],
                        *r["t"])), r["better"], r["equal"], r["worse"], *map(fmt_float, r["block_range"]),
                        " ".join(f"{b}={m:.6g}" for b, m in r["block_means"]), fmt_float(r["p"]), r["method"],
                        fmt_float(r["p_holm"]), fmt_float(r["detectable"]),
                        *map(fmt_float, r.get("spread", (math.nan, math.nan))), t.get("margin", ""),
                        fmt_float(t.get("p", math.nan)), t.get("verdict", "")])
    return csv_text(head, out)


def arms_table(rec: Records, fmt) -> tuple[list[str], list[list]]:
    """Each arm's runs and mean of every quantity some arm has, as ``fmt`` writes a mean."""
    quantities = tuple(q for q in ENDPOINTS + MANIPULATION if any(rec.arm_values(a.key, q) for a in rec.study.arms))
    head = ["arm", "runs", *(NAMES[q] for q in quantities)]
    rows = []
    for arm in rec.study.arms:
        n = len({k for k in rec.values if k[1] == arm.key})
        means = [np.mean(v) if (v := rec.arm_values(arm.key, q)) else math.nan for q in quantities]
        rows.append([f"({arm.key}) {arm.label}", n, *map(fmt, means)])
    return head, rows


def commands(study: Study) -> str:
    """The sweeps `botorl study run` runs, as a reader would type them, then the report."""
    lines = [f"# {study.name}: the sweeps `botorl study run {study.path}` runs, in its order "
             f"(frozen commit {study.commit}); the same by hand:"]
    for block in study.blocks:
        lines.append(f"# block {block.name}" + (" (legacy: its results are its paired.csv)" if block.paired_csv else ""))
        lines += [shlex.join(["botorl", "sweep", *study.sweep_args(block, arm)]) + f"  # ({arm.key}) {arm.label}"
                  for arm in study.arms]
    return "\n".join(lines + [f"botorl study report {shlex.quote(str(study.path))}", ""])


def _plotted(s: Study) -> list[tuple[str, str]]:
    """The comparisons the figure draws; a study without any (descriptive only) has no figure."""
    return list(s.primary) + list(s.secondary) + list(s.floors)


def figure(rec: Records, res: dict[str, list[dict]], names: dict[str, str], path: Path) -> None:
    """Every comparison's paired differences (a dot per pair, a diamond at the mean) per endpoint;
    the floors' 2.5-97.5% ranges shaded."""
    s = rec.study
    comps = _plotted(s)
    plt = pyplot()
    fig, axes = plt.subplots(1, len(s.endpoints), figsize=(5.5 * len(s.endpoints), 1.2 + 0.45 * len(comps)),
                             sharey=True, squeeze=False)
    rng = np.random.default_rng(0)
    for ax, endpoint in zip(axes[0], s.endpoints):
        for i, c in enumerate(comps):
            v = np.asarray(rec.differences(*c, endpoint)[0])
            if len(v):
                ax.scatter(v + rng.uniform(-0.015, 0.015, len(v)), i + rng.uniform(-0.2, 0.2, len(v)), s=12,
                           alpha=0.6, color="tab:gray" if c in s.floors else "tab:blue")
                ax.plot([v.mean()], [i], "D", color="black", ms=6)
        for r in res["floors"]:
            if r["endpoint"] == endpoint and math.isfinite(r["spread"][0]):
                ax.axvspan(*r["spread"], color="tab:gray", alpha=0.08)
        ax.axvline(0, color="black", lw=0.8)
        ax.set_title(NAMES[endpoint])
        ax.set_xlabel("paired difference")
    axes[0][0].set_yticks(range(len(comps)), [" − ".join(names[k] for k in c) for c in comps], fontsize=7)
    axes[0][0].invert_yaxis()
    save_figure(fig, path, f"{s.name}: paired differences per pre-training (dots), their mean (diamond); grey: "
                           "the noise floors, shaded: their 2.5-97.5% range")


def report(study: Study, out: Path) -> list[Path]:
    """analysis.md, comparisons.csv, arms.csv, paired_differences.png, commands.sh and a report
    per block of records (`botorl report` on them) in ``out``."""
    rec = Records(study)
    res = analyse(rec)
    names = {a.key: f"({a.key}) {a.label}" for a in study.arms}
    out.mkdir(parents=True, exist_ok=True)
    files = [atomic_write_text(out / "comparisons.csv", rows_csv(res)),
             atomic_write_text(out / "commands.sh", commands(study))]
    files.append(atomic_write_text(out / "arms.csv", csv_text(*arms_table(rec, fmt_float))))
    if _plotted(study):
        figure(rec, res, names, out / "paired_differences.png")
        files.append(out / "paired_differences.png")
    blocks = []
    for block in study.blocks:
        folders = [d for a in study.arms if (d := study.records_dir(block, a)).is_dir()]
        if block.paired_csv is None and folders:
            make_report(folders, out / block.name, n_boot=study.n_boot, seed=study.boot_seed,
                        dip_window=study.window_end)
            blocks.append(f"[{block.name}]({block.name}/report.md)")
        elif block.paired_csv is not None and (block.paired_csv.parent / "report.md").is_file():
            blocks.append(f"[{block.name}]({os.path.relpath(block.paired_csv.parent / 'report.md', out)})")
    files.append(atomic_write_text(out / "analysis.md", markdown(rec, res, names, blocks)))
    return files


def markdown(rec: Records, res: dict[str, list[dict]], names: dict[str, str], blocks: list[str]) -> str:
    s = rec.study
    n_primary = len(res["primary"])
    lines = [f"# Study {s.name}", "", s.question, "",
             f"Written by `botorl study report` from the study file `{s.path.name}` (frozen commit `{s.commit}`; "
             f"{', '.join(s.tasks)}, profile {s.profile}). Blocks: "
             + ", ".join(f"{b.name} (seeds {seeds_text(b.seeds)})" for b in s.blocks)
             + f". Differences are arm x − arm y per pre-training (same block, task and seed); higher is better. "
             f"Bootstrap: {s.n_boot:,} resamples of the pairs, seed {s.boot_seed}; the dip window ends at "
             f"{s.window_end:g} env steps. The Wilcoxon signed-rank test drops zero differences and is exact without "
             f"ties (n <= 50), else the normal approximation with the tie correction; Holm's correction runs over the "
             f"{n_primary} primary tests. The range of block means is the spread of the blocks, not a confidence "
             "interval. The sweeps, as commands: [commands.sh](commands.sh); every number: "
             "[comparisons.csv](comparisons.csv), [arms.csv](arms.csv).", "", "## Provenance", ""]
    lines += [f"- {n} run(s) record commit `{c}`" + ("" if c.startswith(s.commit) else " (**not the frozen commit**)")
              for c, n in sorted(rec.commits.items())]
    state = read_json_object(s.results / STATE) or {}
    lines += [f"- deviation: `study run` of {inv.get('started')} ran with --unfrozen: {inv['unfrozen']}"
              for inv in state.get("invocations", []) if isinstance(inv, dict) and inv.get("unfrozen")]
    lines += [f"- {note}" for note in rec.notes]
    lines += [f"- not paired: {'/'.join(map(str, k))} and {'/'.join(map(str, p))} start from different pre-trainings "
              "(pretrain_sha256)" for k, p in sorted(rec.unpaired)]
    lines += ["", "## Arms (mean over their runs)", "",
              md_table(*arms_table(rec, lambda v: _num(v, ".2f"))), "",
              f"## Primary comparisons ({n_primary} tests, Holm)", "", comparison_table(res["primary"], names, True), ""]
    if res["secondary"]:
        lines += ["## Secondary comparisons (no correction)", "", comparison_table(res["secondary"], names, False), ""]
    if res["floors"]:
        lines += ["## Noise floors (spread of the paired differences)", "", md_table(
            ["endpoint", "floor", "pairs", "mean", "SD", "2.5-97.5% range"],
            ([NAMES[r["endpoint"]], " − ".join(names[k] for k in r["pair"]),
              r["n"], _num(r["mean"]), _num(r["sd"], ".2f"), fmt_ci(*r["spread"])] for r in res["floors"])),
                  "", "A comparison whose mean lies inside its floor's range is not told from chance by this design.",
                  ""]
    lines += ["## Manipulation check", ""]
    if res["manipulation"]:
        lines += ["Q on the probe's dataset actions and on uniform actions, before the BOTO stage (the pre-trained "
                  "critic) and after it (fine-tuning's first evaluation), per arm; then the change's paired "
                  "difference between arms.", "",
                  md_table(["arm", "runs", "Q data before", "after", "change", "Q uniform before", "after", "change"],
                           ([f"({a.key}) {a.label}", len(rec.arm_values(a.key, 'q_data_change'))]
                            + [_num(np.mean(v), ".3g") if (v := rec.arm_values(a.key, q)) else "-"
                               for q in ("q_data_before", "q_data_after", "q_data_change", "q_uniform_before",
                                         "q_uniform_after", "q_uniform_change")] for a in s.arms)),
                  "", comparison_table(res["manipulation"], names, False), ""]
    else:
        lines += ["The records hold no Q before and after the BOTO stage (a legacy block keeps only its "
                  "paired.csv), so the check cannot be made from them.", ""]
    if blocks:
        lines += ["## Block reports", "", ", ".join(blocks), ""]
    if _plotted(s):
        lines += ["![paired differences](paired_differences.png)", ""]
    return "\n".join(lines)

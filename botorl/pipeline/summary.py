"""A run's summary and curve: each member's ``summary.json`` (and a population's
``population.json``) from its ``eval.csv``, the curve ``curve.png``, and the text ``botorl run``
prints (formats: docs/CONTRACTS.md, "Runs", "Populations").
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from botorl.configs.members import Member
from botorl.configs.methods import get_method
from botorl.configs.schema import RunConfig, to_dict
from botorl.envs.metric import headline_of_summary
from botorl.envs.metric import of_config as metric_of_config
from botorl.errors import BotorlError
from botorl.io import atomic_save_figure, atomic_write_json, pyplot
from botorl.pipeline.provenance import pretrain_sha256
from botorl.pipeline.rundir import EVAL_COLUMNS, POPULATION_FILE, CsvLog, MemberRun, RunDir, read_json


def write_member_summary(member: MemberRun, status: str, stage_seconds: dict, error: str | None = None,
                         population: Path | None = None) -> dict[str, Any]:
    """A member's summary.json (``population``: the folder of the population it is in, None: a
    single run); a member that failed (``member.error``) says so whatever ``status``."""
    if member.error:
        status, error = "failed", member.error
    summary = build_summary(member.cfg, member.run, status, stage_seconds, error)
    if population is not None:
        summary["population"] = str(population)
    atomic_write_json(member.run.summary, summary, root=member.run.root)
    return summary


def write_population_file(root: Path, cfg: RunConfig, member_cfgs: list[RunConfig], status: str,
                          member_status: list[str], stage_seconds: dict, error: str | None = None) -> None:
    uses_alpha = get_method(cfg.method).uses_alpha
    # `name`: the member's run directory as it was made: without --alphas a BOTO member takes the
    # preset's alpha but its directory is seed<k> (`botorl resume POPDIR` reads this name)
    members = [{**Member(c.seed, c.alpha if uses_alpha else None).to_json(), "status": st,
                **({"name": Path(c.out).name} if c.out else {})} for c, st in zip(member_cfgs, member_status)]
    if status == "finished" and any(st != "finished" for st in member_status):
        status = "finished" if any(st == "finished" for st in member_status) else "failed"
    data = {"task": cfg.task, "method": cfg.method, "pretrain": cfg.pretrain, "profile": cfg.profile,
            "status": status, "members": members, "stage_seconds": {k: round(v, 3) for k, v in stage_seconds.items()},
            "total_seconds": round(sum(stage_seconds.values()), 3), "config": to_dict(cfg)}
    if error:
        data["error"] = error
    atomic_write_json(Path(root) / POPULATION_FILE, data, root=root)


def _eval_rows(run: RunDir) -> list[dict[str, float]]:
    rows = []
    for r in CsvLog(run.eval_csv, EVAL_COLUMNS).rows():
        try:
            rows.append({"env_step": int(float(r["env_step"])), "success": float(r["success"]),
                         "return": float(r["return"]), "q_data": float(r["q_data"] or "nan"),
                         "q_uniform": float(r["q_uniform"] or "nan")})
        except (KeyError, TypeError, ValueError):
            continue  # a line cut by a kill
    return sorted(rows, key=lambda r: r["env_step"])


def build_summary(cfg: RunConfig, run: RunDir, status: str, stage_seconds: dict, error: str | None = None) -> dict:
    rows = _eval_rows(run)
    # the evaluations at step 0, at the first at or after 10k online steps (exactly 10k with the
    # presets), and the last one (at online.steps once the run has finished)
    initial = {r["env_step"]: r for r in rows}.get(0)
    after_10k = [r for r in rows if r["env_step"] >= 10_000]
    final = rows[-1] if rows else None
    metric = metric_of_config(cfg)
    # the return always; success or the normalised score where it is the task's metric (absent, not 0, elsewhere)
    points = {}
    for name in (n for n in ("success", "return", "score") if n in ("return", metric.name)):
        for when, row in (("initial", initial), ("10k", after_10k[0] if after_10k else None), ("final", final)):
            points[f"{name}_{when}"] = None if row is None else \
                row["return"] if name == "return" else metric.of(row["success"], row["return"])
    out = {
        "task": cfg.task,
        "method": cfg.method,
        "seed": cfg.seed,
        "alpha": cfg.alpha,
        "pretrain": cfg.pretrain,
        "profile": cfg.profile,
        **points,
        "env_step_10k": after_10k[0]["env_step"] if after_10k else None,
        "env_step_final": final["env_step"] if final else None,
        "q_data_initial": initial["q_data"] if initial else None,
        "q_uniform_initial": initial["q_uniform"] if initial else None,
        "stage_seconds": {k: round(v, 3) for k, v in stage_seconds.items()},
        "total_seconds": round(sum(stage_seconds.values()), 3),
        "online_steps": cfg.online.steps,
        # the pre-trained agent this run starts from: `botorl report` pairs runs by it
        "pretrain_sha256": pretrain_sha256(run.checkpoints),
        "status": status,
        "run_dir": str(run.root),
    }
    if cfg.env.success_off:  # a task of one's own whose env says nothing of success
        out["success_off"] = cfg.env.success_off
    if error:
        out["error"] = error
    return out


def read_summary(run: RunDir) -> dict[str, Any]:
    try:
        summary = read_json(run.summary)
    except (OSError, ValueError) as err:
        raise BotorlError(f"{run.summary} cannot be read ({err}); `botorl resume {run.root}` rewrites it.") from None
    if not isinstance(summary, dict):
        raise BotorlError(f"{run.summary} is not a run summary (a JSON object); `botorl resume {run.root}` "
                          f"rewrites it.")
    return summary


def plot_curves(members: list[MemberRun]) -> None:
    """Each member's curve.png."""
    for member in members:
        try:
            plot_curve(member.run, member.cfg)
        except Exception as err:  # a plot must never fail a run
            print(f"botorl: could not draw {member.run.curve} ({err})", file=sys.stderr)


def plot_curve(run: RunDir, cfg: RunConfig) -> Path | None:
    rows = _eval_rows(run)
    if not rows:
        return None
    plt = pyplot()
    metric = metric_of_config(cfg)
    x = [r["env_step"] for r in rows]
    y = [metric.of(r["success"], r["return"]) for r in rows]
    fig, ax = plt.subplots(figsize=(6, 3.6))
    label = cfg.method if cfg.alpha is None else f"{cfg.method} (alpha={cfg.alpha:+.2f})"
    ax.plot(x, y, marker="o", ms=3, label=label)
    start = cfg.warmup.steps if "warmup" in get_method(cfg.method).stages else 0
    if start > 0:
        ax.axvspan(0, start, color="0.9", label="warm-up (frozen policy, no updates)")
    ax.axvline(start, color="k", ls="--", lw=1, label="fine-tuning starts")
    ax.set_xlabel("online env steps (warm-up included)")
    ax.set_ylabel(metric.label)
    if metric.bounded:
        ax.set_ylim(-0.03, 1.03)
    ax.set_title(f"{cfg.task} / {cfg.method} / seed {cfg.seed}")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    atomic_save_figure(fig, run.curve, root=run.root, dpi=110)
    return run.curve


def _f(v) -> str:
    return "-" if v is None else (f"{v:.3f}" if isinstance(v, float) else str(v))


def format_population(summaries: list[dict]) -> str:
    name = headline_of_summary(summaries[0]) if summaries else "success"
    lines = [f"{'member':<22} {'status':<9} {'initial':>8} {'10k':>8} {'final':>8}  run directory"]
    if name != "success":
        lines.insert(0, f"{name}:")
    for s in summaries:
        member = Path(s["run_dir"]).name
        lines.append(f"{member:<22} {s['status']:<9} {_f(s.get(name + '_initial')):>8} {_f(s.get(name + '_10k')):>8} "
                     f"{_f(s.get(name + '_final')):>8}  {s['run_dir']}")
    secs = summaries[0].get("stage_seconds", {}) if summaries else {}
    lines.append("stage seconds (whole population): " + ", ".join(f"{k} {v:.1f}" for k, v in secs.items()))
    return "\n".join(lines)


def format_summary(summary: dict) -> str:
    name = headline_of_summary(summary)  # the task's headline metric: success, else (normalised) return
    lines = [
        f"task {summary['task']}  method {summary['method']}  seed {summary['seed']}  alpha {_f(summary['alpha'])}  "
        f"pretrain {_f(summary['pretrain'])}  profile {summary.get('profile')}  status {summary['status']}",
        "",
        f"{'stage':<10} {'seconds':>9}",
    ]
    lines += [f"{k:<10} {v:>9.1f}" for k, v in summary["stage_seconds"].items()]
    lines.append(f"{'total':<10} {summary['total_seconds']:>9.1f}")
    lines += [
        "",
        f"{name:<10} {'initial':>8} {'10k':>8} {'final':>8}",
        f"{'':<10} {_f(summary.get(name + '_initial')):>8} {_f(summary.get(name + '_10k')):>8} "
        f"{_f(summary.get(name + '_final')):>8}",
        (f"(10k = eval at env step {summary['env_step_10k']}, final = {_f(summary.get('env_step_final'))})"
         if summary.get("env_step_10k") is not None else
         f"(no evaluation at 10k: the run ends at env step {_f(summary.get('env_step_final'))})"),
        f"run directory: {summary['run_dir']}",
    ]
    if summary.get("success_off"):
        lines.insert(-1, f"success is off: {summary['success_off']}")
    return "\n".join(lines)

"""Drive a run: the method's stages in order, checkpoints, resume, evaluation, summary.

``execute(cfg, run_dir, d_offline_raw, resume=...)`` is what ``botorl run`` and ``botorl
resume`` call after the config is resolved and validated and the offline data are loaded
(so a bad configuration or a missing dataset fails before any work and before a run
directory exists).
"""

from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from botorl.configs.schema import RunConfig, to_dict
from botorl.data.dataset import Dataset
from botorl.errors import ConfigError, TrainingDivergedError
from botorl.pipeline import stages as S
from botorl.pipeline.checkpoint import CheckpointManager, checkpoint_name
from botorl.pipeline.evaluation import QProbe, run_episodes
from botorl.pipeline.methods import get_method
from botorl.pipeline.rundir import EVAL_COLUMNS, CsvLog, MetricsLogger, RunDir, atomic_write_json

_DS_FIELDS = ("observations", "actions", "rewards", "next_observations", "terminals", "episode_ends", "mc_returns")


# ---------------------------------------------------------------------------- data
def load_offline(cfg: RunConfig, spec) -> Dataset:
    """The task's offline data with raw rewards; generated tasks are made when missing."""
    from botorl.data.dataset import validate as validate_dataset

    if spec.dataset_source.kind == "generated" and cfg.data.path is None:
        if cfg.data.demos:
            # the door generator reads the demos from this variable (botorl.data.generators.door)
            demos = Path(cfg.data.demos).expanduser()
            if not demos.is_file():
                raise ConfigError(
                    f"--data.demos {cfg.data.demos}: no such file. Point it at door_human_demos.npz "
                    f"(in a botorl checkout: ../shared/data/adroit/door_human_demos.npz)."
                )
            os.environ["BOTORL_DOOR_DEMOS"] = str(demos.resolve())
        ds = spec.load_dataset(None, steps=cfg.data.steps, seed=cfg.data.seed, progress=cfg.progress)
    else:
        ds = spec.load_dataset(cfg.data.path)
    return validate_dataset(ds, obs_dim=spec.obs_dim, action_dim=spec.action_dim,
                            action_tolerance=cfg.data.action_tolerance)


def transform_dataset(cfg: RunConfig, spec, ds: Dataset) -> Dataset:
    """The task's reward transform, then Cal-QL's Monte-Carlo returns (in transformed units)."""
    return with_mc_returns(cfg, spec, ds.with_reward_transform(spec.reward_transform))


def with_mc_returns(cfg: RunConfig, spec, ds: Dataset) -> Dataset:
    """MC returns of already-transformed rewards (Cal-QL's rule; algorithms.md section 5)."""
    r_neg = cfg.offline.mc_sparse_negative_reward
    gamma = cfg.offline.iql.discount if cfg.pretrain == "iql" else cfg.offline.cql.discount
    return ds.with_mc_returns(
        gamma,
        sparse_negative_reward=None if r_neg is None else float(spec.reward_transform(r_neg)),
        infinite_horizon=cfg.offline.mc_infinite_horizon,
    )


def _dataset_arrays(ds: Dataset) -> dict[str, np.ndarray]:
    return {k: getattr(ds, k) for k in _DS_FIELDS if getattr(ds, k) is not None}


def _dataset_from_arrays(arrays: dict[str, np.ndarray], source: str) -> Dataset:
    return Dataset(
        arrays["observations"], arrays["actions"], arrays["rewards"], arrays["next_observations"],
        arrays["terminals"], arrays["episode_ends"], arrays.get("mc_returns"), metadata={"source": source},
    )


# ---------------------------------------------------------------------------- context
class RunContext:
    """What the stages share: config, task, data, run directory, loggers, checkpoints."""

    def __init__(self, cfg: RunConfig, spec, run: RunDir, d_offline: Dataset, state: dict, wandb_run=None):
        self.cfg = cfg
        self.spec = spec
        self.run = run
        self.d_offline = d_offline
        self.ckpt = CheckpointManager(run.checkpoints)
        self.logger = MetricsLogger(run, tensorboard=cfg.tensorboard, wandb_run=wandb_run)
        self.eval_log = CsvLog(run.eval_csv, EVAL_COLUMNS)
        self.q_log = CsvLog(run.metrics / "q_probe.csv", ["stage", "step", "q_data", "q_uniform"])
        self.probe = QProbe(d_offline.observations, d_offline.actions, seed=12345, size=cfg.eval.q_pairs)
        self.state = state  # done_stages, stage_seconds
        self._envs = None
        self._stage = None
        self._stage_t0 = 0.0

    # -- time
    def begin_stage(self, stage: str) -> None:
        self._stage = stage
        self._stage_t0 = time.perf_counter()
        self.state["stage_seconds"].setdefault(stage, 0.0)

    def stage_seconds(self) -> dict[str, float]:
        out = dict(self.state["stage_seconds"])
        if self._stage is not None:
            out[self._stage] = out.get(self._stage, 0.0) + time.perf_counter() - self._stage_t0
        return out

    def end_stage(self) -> None:
        self.state["stage_seconds"] = self.stage_seconds()
        self._stage = None

    # -- data
    def transform(self, ds: Dataset) -> Dataset:
        return transform_dataset(self.cfg, self.spec, ds)

    def mc_returns(self, ds: Dataset) -> np.ndarray:
        return with_mc_returns(self.cfg, self.spec, ds).mc_returns

    # -- checkpoints
    def load_agent(self, name: str, like):
        from botorl.agents import checkpoint as agent_ckpt

        return agent_ckpt.load(self.ckpt.path(name) / "agent.ckpt", like=like)

    def _save(self, name: str, stage: str, step: int | None, done: bool, agent, np_rng=None, arrays=None, extra=None):
        from botorl.agents import checkpoint as agent_ckpt

        state = {
            "stage": stage,
            "step": step,
            "stage_done": done,
            "done_stages": list(self.state["done_stages"]),
            "stage_seconds": self.stage_seconds(),
            "np_rng": np_rng,
            "extra": extra or {},
            "time": time.time(),
        }
        self.ckpt.save(name, state=state, agent=agent, save_agent=agent_ckpt.save, arrays=arrays)
        self.write_summary("running")

    def save_mid(self, stage: str, step: int, agent, *, np_rng=None, arrays=None, extra=None) -> None:
        self._save(checkpoint_name(stage, step), stage, int(step), False, agent, np_rng, arrays, extra)

    def save_stage_end(self, stage: str, agent, arrays=None) -> None:
        self._save(checkpoint_name(stage, None), stage, None, True, agent, arrays=arrays)

    # -- evaluation
    def envs(self):
        if self._envs is None:
            n = min(self.cfg.eval.num_envs, self.cfg.eval.episodes)
            self._envs = [self.spec.make_env(seed=10_000 + i, evaluation=True) for i in range(n)]
        return self._envs

    def q_stats(self, agent) -> tuple[float, float]:
        return self.probe(S.q_fn(agent))

    def log_q(self, stage: str, step: int, agent) -> None:
        q_data, q_uniform = self.q_stats(agent)
        self.q_log.append({"stage": stage, "step": step, "q_data": q_data, "q_uniform": q_uniform})

    def evaluate(self, agent, env_step: int) -> dict[str, Any]:
        cfg = self.cfg
        stats = run_episodes(
            lambda o: np.asarray(agent.eval_actions(o)), self.envs(), episodes=cfg.eval.episodes,
            success_mode=self.spec.success_mode, seed=100_000 + 1_000 * cfg.seed,
            max_steps=self.spec.max_episode_steps,
        )
        q_data, q_uniform = self.q_stats(agent)
        row = {"stage": self._stage or "finetune", "env_step": int(env_step), "success": stats.success,
               "return": stats.episode_return, "q_data": q_data, "q_uniform": q_uniform}
        self.eval_log.append(row)
        self.logger.log_eval(row)
        return row

    def close(self) -> None:
        for e in self._envs or []:
            e.close()
        self._envs = None
        self.logger.close()

    # -- summary
    def write_summary(self, status: str, error: str | None = None) -> dict[str, Any]:
        summary = build_summary(self.cfg, self.run, status, self.stage_seconds(), error)
        atomic_write_json(self.run.summary, summary)
        return summary


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
    at = {r["env_step"]: r for r in rows}
    initial = at.get(0)
    after_10k = [r for r in rows if r["env_step"] >= 10_000]
    final = rows[-1] if rows else None
    out = {
        "task": cfg.task,
        "method": cfg.method,
        "seed": cfg.seed,
        "alpha": cfg.alpha,
        "pretrain": cfg.pretrain,
        "profile": cfg.profile,
        "success_initial": initial["success"] if initial else None,
        # the first evaluation at or after 10k online steps (exactly 10k with the presets)
        "success_10k": after_10k[0]["success"] if after_10k else None,
        # the last evaluation (at online.steps once the run has finished)
        "success_final": final["success"] if final else None,
        "env_step_10k": after_10k[0]["env_step"] if after_10k else None,
        "env_step_final": final["env_step"] if final else None,
        "q_data_initial": initial["q_data"] if initial else None,
        "q_uniform_initial": initial["q_uniform"] if initial else None,
        "stage_seconds": {k: round(v, 3) for k, v in stage_seconds.items()},
        "total_seconds": round(sum(stage_seconds.values()), 3),
        "online_steps": cfg.online.steps,
        "status": status,
        "run_dir": str(run.root),
    }
    if error:
        out["error"] = error
    return out


# ---------------------------------------------------------------------------- the run
def _template(cfg, stage: str, d: Dataset):
    if stage == "finetune":
        return S.make_online_agent_template(cfg, d.obs_dim, d.action_dim, cfg.seed)
    return S.make_pretrain_agent(cfg, d.obs_dim, d.action_dim, cfg.seed)


def _wandb(cfg: RunConfig, run: RunDir):
    if not cfg.wandb:
        return None
    try:
        import wandb
    except ImportError:
        raise ConfigError("--wandb needs the wandb package: `pip install wandb` (or drop --wandb).") from None
    return wandb.init(project=os.environ.get("WANDB_PROJECT", "botorl"), name=run.root.name, dir=str(run.root),
                      config=to_dict(cfg), resume="allow", id=run.root.name)


def execute(cfg: RunConfig, run: RunDir, d_offline_raw: Dataset, *, resume: bool = False) -> dict[str, Any]:
    from botorl.envs.registry import get_task

    spec = get_task(cfg.task)
    method = get_method(cfg.method)
    run.create()
    d_offline = transform_dataset(cfg, spec, d_offline_raw)
    ckpt = CheckpointManager(run.checkpoints)
    latest = ckpt.latest() if resume else None
    state = {"done_stages": [], "stage_seconds": {}}
    mid = None
    if latest is not None:
        st = ckpt.state(latest["name"])
        state = {"done_stages": list(st["done_stages"]), "stage_seconds": dict(st["stage_seconds"])}
        if not st["stage_done"]:
            mid = {"name": latest["name"], "stage": st["stage"], "step": st["step"], "np_rng": st.get("np_rng"),
                   "extra": st.get("extra", {})}
    wandb_run = _wandb(cfg, run)
    ctx = RunContext(cfg, spec, run, d_offline, state, wandb_run)
    _truncate_logs(ctx, method.stages, mid, state["done_stages"])
    if latest is not None:
        where = f"{mid['stage']} step {mid['step']}" if mid else f"the end of {state['done_stages'][-1]}"
        print(f"botorl: resuming {run.root} from {where} (checkpoint {latest['name']})", file=sys.stderr)
    ctx.write_summary("running")

    agent = None
    d_warmup = None
    if state["done_stages"]:
        last = state["done_stages"][-1]
        agent = ctx.load_agent(checkpoint_name(last, None), _template(cfg, last, d_offline))
    if "warmup" in state["done_stages"]:
        arrays = ckpt.arrays(checkpoint_name("warmup", None), "warmup")
        d_warmup = _dataset_from_arrays(arrays, "D_warmup (checkpoint)") if arrays else None

    try:
        for stage in method.stages:
            if stage in state["done_stages"]:
                continue
            resume_here = mid if (mid is not None and mid["stage"] == stage) else None
            ctx.begin_stage(stage)
            arrays = None
            if stage == "pretrain":
                agent = S.pretrain(ctx, resume_here)
                ctx.log_q("pretrain", cfg.offline.steps, agent)
            elif stage == "warmup":
                d_warmup, agent = S.warmup(ctx, agent)
                arrays = {"warmup": _dataset_arrays(d_warmup)} if d_warmup is not None else None
            elif stage == "boto":
                if resume_here is not None and agent is None:
                    agent = _template(cfg, "boto", d_offline)
                agent = S.boto(ctx, agent, d_warmup, resume_here)
                ctx.log_q("boto", cfg.boto.boto_steps, agent)
            elif stage == "finetune":
                if agent is None:  # rlpd, or a resume inside fine-tuning of a method without pre-training
                    agent = _template(cfg, "pretrain", d_offline) if "pretrain" in method.stages else None
                agent = S.finetune(ctx, agent, d_warmup, resume_here)
            ctx.end_stage()
            state["done_stages"].append(stage)
            ctx.save_stage_end(stage, agent, arrays=arrays)
    except TrainingDivergedError as err:
        ctx.end_stage()
        ctx.write_summary("failed", error=str(err))
        _finish_outputs(ctx)
        ctx.close()
        raise
    except BaseException as err:  # an interrupt or a bug: the run can be resumed
        ctx.end_stage()
        status = "running" if isinstance(err, KeyboardInterrupt) else "failed"
        ctx.write_summary(status, error=None if status == "running" else f"{type(err).__name__}: {err}")
        ctx.close()
        raise
    summary = ctx.write_summary("finished")
    _finish_outputs(ctx)
    ctx.close()
    if wandb_run is not None:
        wandb_run.finish()
    return summary


def _truncate_logs(ctx: RunContext, stages: tuple[str, ...], mid: dict | None, done: list[str]) -> None:
    """Forget log rows written after the checkpoint a resume starts from."""
    def num(r, key):
        try:
            return float(r.get(key))
        except (TypeError, ValueError):
            return math.inf

    for stage in stages:
        if stage in done:
            continue
        keep_to = int(mid["step"]) if (mid is not None and mid["stage"] == stage) else -1
        ctx.logger.truncate(stage, keep_to)
    ft_keep = int(mid["step"]) if (mid is not None and mid["stage"] == "finetune") else -1
    if "finetune" not in done:
        # evaluations of finished stages (the warm-up's) stay; fine-tuning's up to its checkpoint
        ctx.eval_log.truncate(lambda r: r.get("stage") in done or num(r, "env_step") <= ft_keep)
    ctx.q_log.truncate(lambda r: r.get("stage") in done)


def _finish_outputs(ctx: RunContext) -> None:
    try:
        plot_curve(ctx.run, ctx.cfg)
    except Exception as err:  # a plot must never fail a run
        print(f"botorl: could not draw curve.png ({err})", file=sys.stderr)


def plot_curve(run: RunDir, cfg: RunConfig) -> Path | None:
    rows = _eval_rows(run)
    if not rows:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [r["env_step"] for r in rows]
    y = [r["success"] for r in rows]
    fig, ax = plt.subplots(figsize=(6, 3.6))
    label = cfg.method if cfg.alpha is None else f"{cfg.method} (alpha={cfg.alpha:+.2f})"
    ax.plot(x, y, marker="o", ms=3, label=label)
    method = get_method(cfg.method)
    start = cfg.warmup.steps if "warmup" in method.stages else 0
    if start > 0:
        ax.axvspan(0, start, color="0.9", label="warm-up (frozen policy, no updates)")
    ax.axvline(start, color="k", ls="--", lw=1, label="fine-tuning starts")
    ax.set_xlabel("online env steps (warm-up included)")
    ax.set_ylabel("success")
    ax.set_ylim(-0.03, 1.03)
    ax.set_title(f"{cfg.task} / {cfg.method} / seed {cfg.seed}")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    from botorl.io import atomic_write_bytes

    atomic_write_bytes(run.curve, buf.getvalue())
    return run.curve


def format_summary(summary: dict) -> str:
    def f(v):
        return "-" if v is None else (f"{v:.3f}" if isinstance(v, float) else str(v))

    lines = [
        f"task {summary['task']}  method {summary['method']}  seed {summary['seed']}  alpha {f(summary['alpha'])}  "
        f"pretrain {f(summary['pretrain'])}  profile {summary.get('profile')}  status {summary['status']}",
        "",
        f"{'stage':<10} {'seconds':>9}",
    ]
    for k, v in summary["stage_seconds"].items():
        lines.append(f"{k:<10} {v:>9.1f}")
    lines.append(f"{'total':<10} {summary['total_seconds']:>9.1f}")
    lines += [
        "",
        f"{'success':<10} {'initial':>8} {'10k':>8} {'final':>8}",
        f"{'':<10} {f(summary['success_initial']):>8} {f(summary['success_10k']):>8} {f(summary['success_final']):>8}",
        f"(10k = eval at env step {f(summary.get('env_step_10k'))}, final = {f(summary.get('env_step_final'))})",
        f"run directory: {summary['run_dir']}",
    ]
    return "\n".join(lines)

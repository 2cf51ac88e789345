"""Drive a run: the method's stages in order, checkpoints, resume, evaluation, summary.

``execute`` is called by ``botorl run`` / ``resume`` once the config is validated and the data
loaded, so a bad config or a missing dataset fails before a run directory exists.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np
from tqdm.auto import tqdm

from botorl.agents import agent_file
from botorl.agents import population
from botorl.configs.members import Member, Streams
from botorl.configs.methods import get_method
from botorl.configs.schema import RunConfig, to_dict
from botorl.data.dataset import FIELDS, Dataset, RewardTransform
from botorl.data.dataset import validate as validate_dataset
from botorl.data.loaders import refuse_pickle
from botorl.data.tasks import load_task_data
from botorl.envs.metric import headline_of_summary
from botorl.envs.metric import of_config as metric_of_config
from botorl.envs.registry import get_task
from botorl.errors import BotorlError, ConfigError, Interrupted, TrainingDivergedError
from botorl.io import atomic_save_figure, atomic_write_json, pyplot
from botorl.jaxsetup import matmul_precision
from botorl.pipeline import evaluation, preempt, shared_pretrain, tracking
from botorl.pipeline import stages
from botorl.pipeline.checkpoint import CheckpointManager, check_identity, checkpoint_name, full_identity
from botorl.pipeline.evaluation import QProbe, make_eval_envs
from botorl.pipeline.rundir import EVAL_COLUMNS, POPULATION_FILE, CsvLog, MetricsLogger, RunDir, number, read_json
from botorl.pipeline.provenance import pretrain_sha256


# ---------------------------------------------------------------------------- data
def load_offline(cfg: RunConfig, spec) -> Dataset:
    """The task's offline data with raw rewards; generated tasks are made when missing."""
    if spec.dataset_source.kind == "generated" and cfg.data.path is None:
        if cfg.data.demos:
            # the door generator reads the demos from this variable (botorl.data.generators.door)
            demos = Path(cfg.data.demos).expanduser()
            if not demos.is_file():
                raise ConfigError(
                    f"--data.demos {cfg.data.demos}: no such file. Point it at a door_human_demos.npz (the DAPG "
                    f"door demos), or leave --demos out: botorl then uses the copy it ships "
                    f"(botorl/data/assets/door_human_demos.npz)."
                )
            os.environ["BOTORL_DOOR_DEMOS"] = str(demos.resolve())
        ds = load_task_data(spec, None, steps=cfg.data.steps, seed=cfg.data.seed, progress=cfg.progress)
    else:  # a user's task: its actions checked against the env's box, as every dataset's
        ds = load_task_data(spec, cfg.data.path, action_tolerance=cfg.data.action_tolerance)
    return validate_dataset(ds, obs_dim=spec.obs_dim, action_dim=spec.action_dim,
                            action_tolerance=cfg.data.action_tolerance)


def load_run_data(cfg: RunConfig, origin: Path, allow_pickle: bool = False) -> Dataset:
    """The offline data of a run or population read back from its directory's ``origin``
    (config.json, population.json): no pickle unless allowed, as a pickle there could run code."""
    where = "population" if origin.name == POPULATION_FILE else "run"
    with contextlib.nullcontext() if allow_pickle else refuse_pickle(f"the {where} directory's {origin}"):
        return load_offline(cfg, get_task(cfg.task))


def transform_dataset(cfg: RunConfig, spec, ds: Dataset) -> Dataset:
    """The task's reward transform, then Cal-QL's Monte-Carlo returns (in transformed units)."""
    return with_mc_returns(cfg, spec, ds.with_reward_transform(RewardTransform.of(spec)))


def with_mc_returns(cfg: RunConfig, spec, ds: Dataset) -> Dataset:
    """MC returns of already-transformed rewards (Cal-QL's rule; docs/methods.md)."""
    r_neg = cfg.offline.mc_sparse_negative_reward
    gamma = cfg.offline.iql.discount if cfg.pretrain == "iql" else cfg.offline.cql.discount
    return ds.with_mc_returns(
        gamma,
        sparse_negative_reward=None if r_neg is None else float(RewardTransform.of(spec)(r_neg)),
        infinite_horizon=cfg.offline.mc_infinite_horizon,
    )


# ---------------------------------------------------------------------------- context
class MemberRun:
    """One member of a population: its own config (seed, alpha), run directory and logs."""

    def __init__(self, cfg: RunConfig, run: RunDir, wandb_run=None, error: str | None = None):
        self.cfg = cfg
        self.run = run
        run.create()
        self.logger = MetricsLogger(run, tensorboard=cfg.tensorboard, wandb_run=wandb_run)
        self.eval_log = CsvLog(run.eval_csv, EVAL_COLUMNS)
        self.q_log = CsvLog(run.metrics / "q_probe.csv", ["stage", "step", "q_data", "q_uniform"])
        self.error = error  # set when this member diverged (the others go on)


class RunContext:
    """What the stages share: the members (each its config, run directory and logs), the
    method and task, the offline data (held once) and its probe, evaluation, the divergence
    check, and the population's checkpoints (formats: docs/CONTRACTS.md "Runs", "Populations";
    a single run keeps the single-run format, its values stored plain, not as lists)."""

    def __init__(self, cfg: RunConfig, spec, root: Path, members: list[MemberRun], d_offline: Dataset, state: dict):
        self.cfg, self.method, self.spec = cfg, get_method(cfg.method), spec
        self.root, self.members, self.n = Path(root), members, len(members)
        self.single = members[0].run.root == self.root
        self.ckpt = CheckpointManager(RunDir(root).checkpoints)
        self.d_offline = d_offline
        self.probe = QProbe(d_offline.observations, d_offline.actions, seed=Streams.PROBE, size=cfg.eval.q_pairs)
        self.state = state  # done_stages, stage_seconds
        self.failed: set[int] = {i for i, m in enumerate(members) if m.error}
        self._envs = None
        self.loop = None  # the online loop's state (stages.online_state), from the warm-up to fine-tuning's end
        self._stage = None
        self._stage_t0 = 0.0

    def live(self, ms: list):
        """(member, its item of ``ms``) for the members that have not failed."""
        return [(member, m) for i, (member, m) in enumerate(zip(self.members, ms)) if i not in self.failed]

    def log(self, stage: str, step: int, rows: list[dict]) -> None:
        """Each live member's row of ``rows`` into its metrics/<stage> logs."""
        for member, row in self.live(rows):
            member.logger.log(stage, step, row)

    def check(self, stage: str, step: int, ms: list[dict[str, float]]) -> None:
        """Each live member's metrics must be finite: a population of one raises (the last good
        checkpoint stays); in a larger one a diverged member is marked failed and the rest go on."""
        bad = [", ".join(f"{k} = {v}" for k, v in sorted(m.items()) if not math.isfinite(v)) for m in ms]
        diverged = f"training diverged in stage {stage!r} near step {step}: "
        for i, b in enumerate(bad):
            if not b or i in self.failed:
                continue
            if self.n == 1:
                last = self.ckpt.latest()
                where = f"checkpoint {last['name']}" if last else "no checkpoint yet"
                raise TrainingDivergedError(
                    f"{diverged}{b}. The last good state is kept ({where} in {self.ckpt.root}). Lower the "
                    f"learning rates (e.g. --offline.cql.critic_lr, --online.sac.critic_lr), check the data's reward "
                    f"scale, or run another seed; `botorl resume` would start again from that checkpoint.")
            self.failed.add(i)
            self.members[i].error = f"{diverged}{b}. The other members went on. Lower the learning rates or run another seed."
            self.write_member_summary(i, "failed")
            print(f"botorl: member {self.members[i].run.root.name} failed: {self.members[i].error}", file=sys.stderr)
        if len(self.failed) == self.n:
            raise TrainingDivergedError(
                f"every member of the population diverged (stage {stage!r}, near step {step}); each member's "
                f"summary.json says how. Lower the learning rates (e.g. --online.sac.critic_lr) or check the data's "
                f"reward scale.")

    def bar(self, total: int, initial: int, desc: str, unit: str = "step"):
        return tqdm(total=total, initial=initial, desc=desc, unit=unit, dynamic_ncols=True,
                    disable=not self.cfg.progress, mininterval=1.0, smoothing=0.05)

    # -- time
    def begin_stage(self, stage: str) -> None:
        self._stage = stage
        self._stage_t0 = time.perf_counter()

    def stage_seconds(self) -> dict[str, float]:
        out = dict(self.state["stage_seconds"])
        if self._stage is not None:
            out[self._stage] = out.get(self._stage, 0.0) + time.perf_counter() - self._stage_t0
        return out

    def end_stage(self) -> None:
        self.state["stage_seconds"] = self.stage_seconds()
        self._stage = None

    # -- data
    def mc_returns(self, ds: Dataset) -> np.ndarray:
        """The MC returns of an episode or D_warmup by the offline data's rule: the online loop's."""
        return with_mc_returns(self.cfg, self.spec, ds).mc_returns

    # -- checkpoints
    def load_agents(self, name: str, like):
        """The population's agents saved under ``name`` (``like``: a stacked template)."""
        path = self.ckpt.file(name, "agent.ckpt")
        if self.single:  # the member's own agent
            return population.stack([agent_file.load(path, like=population.member_of(like, 0))])
        return agent_file.load(path, like=like)

    def _stored(self, x):
        """Per-member lists (alone, or as the values of a dict) as a single run stores them: its item."""
        if isinstance(x, dict):
            return {k: self._stored(v) for k, v in x.items()}
        return x[0] if self.single and isinstance(x, list) else x

    def warmup_keys(self) -> list[str]:
        return ["warmup"] if self.single else [f"warmup-m{i}" for i in range(self.n)]

    def save(self, stage: str, step: int | None, agents, saved: dict | None = None) -> None:
        """A checkpoint of ``stage`` at ``step`` (None: its end): the agents and the stage's state
        dict ``saved`` (each member's generator state ``np_rng``, ``extra`` counters in state.json,
        ``arrays`` npz groups, ``documents`` JSON files; the warm-up's end: the online loop's)."""
        saved, name, done = saved or {}, checkpoint_name(stage, step), step is None
        state = {
            "identity": [full_identity(member.cfg) for member in self.members],
            "stage": stage,
            "step": None if done else int(step),
            "stage_done": done,
            "done_stages": list(self.state["done_stages"]),
            "stage_seconds": self.stage_seconds(),
            "np_rng": self._stored(saved.get("np_rng")),
            "extra": self._stored(saved.get("extra") or {}),
            "failed": {str(i): self.members[i].error for i in sorted(self.failed)},
            "time": time.time(),
        }
        self.ckpt.save(name, state=state, agent=population.member_of(agents, 0) if self.single else agents,
                       save_agent=agent_file.save, arrays=saved.get("arrays"), documents=saved.get("documents"))
        if not self.single and done:
            # each member's own agent in its run directory, for `botorl eval MEMBER_DIR`
            for i, member in enumerate(self.members):
                CheckpointManager(member.run.checkpoints).save(
                    name, state={**state, "np_rng": None, "extra": {}, "member": i, "identity": [state["identity"][i]]},
                    agent=population.member_of(agents, i), save_agent=agent_file.save)
        self.write_summary("running")

    def contents(self, point: dict) -> dict:
        """What a stage resumes from: the checkpoint ``point`` names (``_resume_point``), its
        arrays and documents read whole, and ``agents(like)``, its agents loaded on a template
        of the stage's (the stage knows their structure)."""
        root, st = self.ckpt.root / point["name"], self.ckpt.state(point["name"])
        return {"step": st["step"], "np_rng": st.get("np_rng"), "extra": st.get("extra", {}), **point,
                "arrays": {p.stem: self.ckpt.arrays(point["name"], p.stem) for p in sorted(root.glob("*.npz"))},
                "documents": {p.stem: self.ckpt.document(point["name"], p.stem) for p in sorted(root.glob("*.json"))
                              if p.stem not in ("state", "MANIFEST")},
                "agents": lambda like: self.load_agents(point["name"], like)}

    # -- evaluation
    def q_stats(self, agents) -> list[tuple[float, float]]:
        """(q_data, q_uniform) per member on the probe's pairs (one call for all members)."""
        q_d = jax.device_get(population.q_mean(agents, self.probe.observations, self.probe.actions))
        q_u = jax.device_get(population.q_mean(agents, self.probe.observations, self.probe.uniform))
        return [(float(q_d[i].mean()), float(q_u[i].mean())) for i in range(self.n)]

    def log_q(self, stage: str, step: int, agents) -> None:
        for member, (q_data, q_uniform) in self.live(self.q_stats(agents)):
            member.q_log.append({"stage": stage, "step": step, "q_data": q_data, "q_uniform": q_uniform})

    def evaluate(self, agents, env_step: int) -> list[dict[str, Any]]:
        """All members' evaluation episodes, one batched policy call per env step; a row per member."""
        cfg = self.cfg
        if self._envs is None:  # each member's evaluation envs (the same seeds for every member), kept
            self._envs = [make_eval_envs(self.spec, cfg.eval) for _ in self.members]
        stats = evaluation.run_episodes(
            lambda o: jax.device_get(population.eval_actions(agents, o)), self._envs, episodes=cfg.eval.episodes,
            success_mode=self.spec.success_mode, seeds=[Streams.of(member.cfg).evaluation for member in self.members],
            max_steps=self.spec.max_episode_steps,
        )
        qs = self.q_stats(agents)
        rows = [{"stage": self._stage or "finetune", "env_step": int(env_step), "success": st.success,
                 "return": st.episode_return, "q_data": q_data, "q_uniform": q_uniform}
                for st, (q_data, q_uniform) in zip(stats, qs)]
        return self.log_evaluation(rows)

    def log_evaluation(self, rows: list[dict[str, Any]], env_step: int | None = None) -> list[dict[str, Any]]:
        """Log one row per member (at ``env_step`` if given: an earlier evaluation of the same,
        unchanged policies, which deterministic episodes from the same seeds would repeat)."""
        if env_step is not None:
            rows = [dict(r, env_step=int(env_step)) for r in rows]
        for member, row in self.live(rows):
            member.eval_log.append(row)
            member.logger.log_eval(row)
        return rows

    def close(self) -> None:
        if self.loop is not None:  # its envs, when a stage stopped before fine-tuning closed them
            self.loop.__exit__()
        for es in self._envs or []:
            for e in es:
                e.close()
        self._envs = None
        for member in self.members:
            member.logger.close()

    # -- summary
    def write_member_summary(self, i: int, status: str, error: str | None = None) -> dict[str, Any]:
        member = self.members[i]
        if i in self.failed:
            status, error = "failed", member.error
        summary = build_summary(member.cfg, member.run, status, self.stage_seconds(), error)
        if not self.single:
            summary["population"] = str(self.root)
        atomic_write_json(member.run.summary, summary)
        return summary

    def write_summary(self, status: str, error: str | None = None) -> None:
        """Every member's summary.json (and a population's population.json)."""
        out = [self.write_member_summary(i, status, error) for i in range(self.n)]
        if not self.single:
            write_population_file(self.root, self.cfg, [member.cfg for member in self.members], status,
                                  [s["status"] for s in out], self.stage_seconds(), error)


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
    atomic_write_json(Path(root) / POPULATION_FILE, data)


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


# ---------------------------------------------------------------------------- the run
def _templates(member_cfgs: list[RunConfig], stage: str, d: Dataset):
    return population.stack([stages.agent_template(c, stage, d.obs_dim, d.action_dim, c.seed) for c in member_cfgs])


def _resume_point(ckpt: CheckpointManager, member_cfgs: list[RunConfig], resume: bool):
    """(the newest checkpoint, {done_stages, stage_seconds}, failed members, the mid-stage point or None)."""
    latest = ckpt.latest() if resume else None
    if latest is None:
        return None, {"done_stages": [], "stage_seconds": {}}, {}, None
    st = ckpt.state(latest["name"])
    check_identity(st, [full_identity(c) for c in member_cfgs], ckpt.root, latest["name"])
    mid = None if st["stage_done"] else {"name": latest["name"], "stage": st["stage"], "step": st["step"]}
    return latest, {"done_stages": list(st["done_stages"]), "stage_seconds": dict(st["stage_seconds"])}, \
        st.get("failed") or {}, mid


def _run_stage(ctx: RunContext, stage: str, agents, d_warmups, resume: dict | None):
    """One stage of the method, given its inputs (and any checkpoint it resumes from, read here):
    (agents, D_warmups, what its end-of-stage checkpoint keeps). The online loop's state
    (``ctx.loop``) is made at the warm-up's start and kept for fine-tuning."""
    cfg, end, member_cfgs, d = ctx.cfg, None, [member.cfg for member in ctx.members], ctx.d_offline
    hooks = stages.Hooks(ctx.log, ctx.check, ctx.bar, ctx.evaluate, ctx.log_evaluation, ctx.save)
    resume = None if resume is None else ctx.contents(resume)
    if stage == "pretrain":
        if cfg.pretrained is not None:  # the same numbers another run computed (shared_pretrain.py)
            agents = shared_pretrain.load(ctx, shared_pretrain.match(member_cfgs, cfg.pretrained))
        else:
            agents = stages.pretrain(cfg, member_cfgs, d, hooks, resume)
        ctx.log_q("pretrain", cfg.offline.steps, agents)
    elif stage == "warmup":  # the online loop starts here, and fine-tuning goes on with it
        ctx.loop = stages.online_state(cfg, member_cfgs, ctx.method, ctx.spec, d, ctx.mc_returns)
        d_warmups, agents = stages.warmup(cfg, member_cfgs, agents, ctx.loop, hooks)
        if d_warmups is not None:  # its end's checkpoint: the loop's state, and D_warmup for BOTO
            end = ctx.loop.state_dict()
            end["arrays"].update({k: dw.arrays() for k, dw in zip(ctx.warmup_keys(), d_warmups)})
    elif stage == "boto":
        if resume is not None and agents is None:
            agents = _templates(member_cfgs, "boto", d)
        agents = stages.boto(cfg, member_cfgs, agents, d, d_warmups, hooks, resume)
        ctx.log_q("boto", cfg.boto.boto_steps, agents)
    elif stage == "finetune":
        if agents is None:  # rlpd, or a resume inside fine-tuning of a method without pre-training
            agents = _templates(member_cfgs, "pretrain", d) if ctx.method.pretrains else None
        if ctx.loop is None:  # a method without a warm-up, or a run resumed after it: from its checkpoint
            ctx.loop = stages.online_state(cfg, member_cfgs, ctx.method, ctx.spec, d, ctx.mc_returns)
            warm = "warmup" in ctx.method.stages and cfg.warmup.steps > 0
            saved = resume or (ctx.contents({"name": checkpoint_name("warmup", None)}) if warm else None)
            if saved is not None:
                ctx.loop.load_state_dict(saved)
        agents = stages.finetune(cfg, member_cfgs, ctx.method, agents, ctx.loop, ctx.probe.observations, hooks, resume)
    return agents, d_warmups, end


def execute(cfg: RunConfig, member_cfgs: list[RunConfig], root: Path, member_runs: list[RunDir],
            d_offline_raw: Dataset, *, resume: bool = False) -> list[dict[str, Any]]:
    """Train the members (configs that differ in seed and alpha only) as one population whose
    checkpoints are in ``root`` (a single run: one member, whose run directory is ``root``);
    returns every member's summary."""
    spec, method, root = get_task(cfg.task), get_method(cfg.method), Path(root)
    root.mkdir(parents=True, exist_ok=True)
    d_offline = transform_dataset(cfg, spec, d_offline_raw)
    ckpt = CheckpointManager(RunDir(root).checkpoints)
    latest, state, failed, mid = _resume_point(ckpt, member_cfgs, resume)
    wandb_runs = tracking.start(member_cfgs, member_runs)  # one W&B run per member (None: no --wandb)
    members = [MemberRun(c, r, w, failed.get(str(i)))
               for i, (c, r, w) in enumerate(zip(member_cfgs, member_runs, wandb_runs))]
    ctx = RunContext(cfg, spec, root, members, d_offline, state)
    for member in members:
        _truncate_logs(member, method.stages, mid, state["done_stages"])
    if latest is not None:
        where = f"{mid['stage']} step {mid['step']}" if mid else f"the end of {state['done_stages'][-1]}"
        print(f"botorl: resuming {root} from {where} (checkpoint {latest['name']})", file=sys.stderr)
    ctx.write_summary("running")

    agents = d_warmups = None
    try:
        # SIGTERM / SIGINT: the stages stop at a step with a checkpoint; every matmul at the
        # config's precision (traced inside, so every jitted call of the stages follows it)
        with preempt.deferred(), matmul_precision(cfg.precision):
            if state["done_stages"]:
                last = state["done_stages"][-1]
                agents = ctx.load_agents(checkpoint_name(last, None), _templates(member_cfgs, last, d_offline))
            if "warmup" in state["done_stages"]:
                d_warmups = _load_warmups(ckpt, ctx.warmup_keys())
            for stage in method.stages:
                if stage in state["done_stages"]:
                    continue
                if preempt.requested():  # between two stages: the last one's final checkpoint is the point
                    raise preempt.interrupted()
                ctx.begin_stage(stage)
                resume_at = mid if (mid is not None and mid["stage"] == stage) else None
                agents, d_warmups, end = _run_stage(ctx, stage, agents, d_warmups, resume_at)
                ctx.end_stage()
                state["done_stages"].append(stage)
                ctx.save(stage, None, agents, end)
    except BaseException as err:  # a signal, a divergence, a Ctrl-C or a bug: the run can be resumed
        ctx.end_stage()
        if isinstance(err, Interrupted):
            ctx.write_summary("interrupted")
        elif isinstance(err, TrainingDivergedError):
            ctx.write_summary("failed", error=str(err))
            _finish_outputs(ctx)
        else:
            ctx.write_summary("interrupted" if isinstance(err, KeyboardInterrupt) else "failed",
                              error=f"{type(err).__name__}: {err}")
        ctx.close()
        if not isinstance(err, Interrupted):
            tracking.finish(wandb_runs, 1)
            raise
        latest = ctx.ckpt.latest()
        err.checkpoint = latest["name"] if latest else None
        tracking.finish(wandb_runs, 128 + err.signum, seconds=min(tracking.timeout(), 10.0))
        raise
    ctx.write_summary("finished")
    summaries = [read_summary(member.run) for member in members]
    _finish_outputs(ctx)
    ctx.close()
    tracking.finish(wandb_runs)
    return summaries


def read_summary(run: RunDir) -> dict[str, Any]:
    try:
        summary = read_json(run.summary)
    except (OSError, ValueError) as err:
        raise BotorlError(f"{run.summary} cannot be read ({err}); `botorl resume {run.root}` rewrites it.") from None
    if not isinstance(summary, dict):
        raise BotorlError(f"{run.summary} is not a run summary (a JSON object); `botorl resume {run.root}` "
                          f"rewrites it.")
    return summary


def _load_warmups(ckpt: CheckpointManager, keys: list[str]) -> list[Dataset] | None:
    saved = [ckpt.arrays(checkpoint_name("warmup", None), key) for key in keys]
    if not all(saved):
        return None
    return [Dataset(**{k: a.get(k) for k in FIELDS}, metadata={"source": "D_warmup (checkpoint)"}) for a in saved]


def _truncate_logs(member: "MemberRun", order: tuple[str, ...], mid: dict | None, done: list[str]) -> None:
    """Forget a member's log rows written after the checkpoint a resume starts from."""
    def kept(stage: str) -> int:  # the last step of a stage's logs that stays: its mid-stage checkpoint's
        return int(mid["step"]) if (mid is not None and mid["stage"] == stage) else -1

    for stage in order:
        if stage not in done:
            member.logger.truncate(stage, kept(stage))
    if "finetune" not in done:
        # evaluations of finished stages (the warm-up's) stay; fine-tuning's up to its checkpoint
        member.eval_log.truncate(lambda r: r.get("stage") in done or number(r.get("env_step")) <= kept("finetune"))
    member.q_log.truncate(lambda r: r.get("stage") in done)


def _finish_outputs(ctx: RunContext) -> None:
    for member in ctx.members:
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
    atomic_save_figure(fig, run.curve, dpi=110)
    plt.close(fig)
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

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

from botorl.agents import agent_file, population
from botorl.configs.members import Streams
from botorl.configs.methods import get_method
from botorl.configs.schema import RunConfig
from botorl.data.dataset import FIELDS, Dataset, RewardTransform
from botorl.data.dataset import validate as validate_dataset
from botorl.data.loaders import refuse_pickle
from botorl.data.tasks import load_task_data
from botorl.envs.registry import get_task
from botorl.errors import ConfigError, Interrupted, TrainingDivergedError
from botorl.jaxsetup import matmul_precision
from botorl.pipeline import evaluation, preempt, shared_pretrain, stages, summary, tracking
from botorl.pipeline.checkpoint import CheckpointManager, checkpoint_name, full_identity, resume_point
from botorl.pipeline.evaluation import QProbe, make_eval_envs
from botorl.pipeline.online import OnlineState
from botorl.pipeline.rundir import POPULATION_FILE, MemberRun, RunDir


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
class RunContext:
    """What the stages share: the members (each its config, run directory and logs), the
    method and task, the offline data (held once) and its probe, evaluation, the divergence
    check, and the population's checkpoints (formats: docs/CONTRACTS.md "Runs", "Populations";
    a single run keeps the single-run format, its values stored plain, not as lists)."""

    def __init__(self, cfg: RunConfig, spec, root: Path, members: list[MemberRun], d_offline: Dataset, state: dict):
        self.cfg, self.method, self.spec = cfg, get_method(cfg.method), spec
        self.root, self.members, self.n = Path(root), members, len(members)
        self.member_cfgs = [member.cfg for member in members]
        self.single = members[0].run.root == self.root
        self.population = None if self.single else self.root  # where population.json is
        self.ckpt = CheckpointManager(RunDir(root).checkpoints)
        self.d_offline = d_offline
        self.probe = QProbe(d_offline.observations, d_offline.actions, seed=Streams.PROBE, size=cfg.eval.q_pairs)
        self.state = state  # done_stages, stage_seconds
        self._envs = None
        self.loop = None  # the online loop's state (online_loop), from the warm-up to fine-tuning's end
        self.d_warmups = None  # each member's D_warmup: the warm-up's, or its checkpoint's on a resume after it
        self._stage = None
        self._stage_t0 = 0.0

    def live(self, ms: list):
        """(member, its item of ``ms``) for the members that have not failed (a failed one has its error)."""
        return [(member, m) for member, m in zip(self.members, ms) if not member.error]

    def log(self, stage: str, step: int, rows: list[dict]) -> None:
        """Each live member's row of ``rows`` into its metrics/<stage> logs."""
        for member, row in self.live(rows):
            member.logger.log(stage, step, row)

    def check(self, stage: str, step: int, ms: list[dict[str, float]]) -> None:
        """Each live member's metrics must be finite: a population of one raises (the last good
        checkpoint stays); in a larger one a diverged member is marked failed and the rest go on."""
        bad = [", ".join(f"{k} = {v}" for k, v in sorted(m.items()) if not math.isfinite(v)) for m in ms]
        diverged = f"training diverged in stage {stage!r} near step {step}: "
        for member, b in zip(self.members, bad):
            if not b or member.error:
                continue
            if self.n == 1:
                last = self.ckpt.latest()
                where = f"checkpoint {last['name']}" if last else "no checkpoint yet"
                raise TrainingDivergedError(
                    f"{diverged}{b}. The last good state is kept ({where} in {self.ckpt.root}). Lower the "
                    f"learning rates (e.g. --offline.cql.critic_lr, --online.sac.critic_lr), check the data's reward "
                    f"scale, or run another seed; `botorl resume` would start again from that checkpoint.")
            member.error = f"{diverged}{b}. The other members went on. Lower the learning rates or run another seed."
            summary.write_member_summary(member, "failed", self.stage_seconds(), population=self.population)
            print(f"botorl: member {member.run.root.name} failed: {member.error}", file=sys.stderr)
        if all(member.error for member in self.members):
            raise TrainingDivergedError(
                f"every member of the population diverged (stage {stage!r}, near step {step}); each member's "
                f"summary.json says how. Lower the learning rates (e.g. --online.sac.critic_lr) or check the data's "
                f"reward scale.")

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

    def online_loop(self, resume: dict | None = None) -> OnlineState:
        """The online loop's state (stages.online_state), made at the warm-up's start and kept to
        fine-tuning's end; one made at fine-tuning's start (a method without a warm-up, or a run
        resumed after it) is restored from its checkpoint: ``resume``'s, else the warm-up's end."""
        if self.loop is None:
            self.loop = stages.online_state(self.cfg, self.member_cfgs, self.method, self.spec, self.d_offline,
                                            self.mc_returns)
            warm = "warmup" in self.state["done_stages"] and self.cfg.warmup.steps > 0
            saved = resume or (self.contents({"name": checkpoint_name("warmup", None)}) if warm else None)
            if saved is not None:
                self.loop.load_state_dict(saved)
        return self.loop

    # -- checkpoints
    def load_pretrained(self):
        """The members' agents pre-trained by the runs ``--pretrained`` names (shared_pretrain.py)."""
        return shared_pretrain.load(self, shared_pretrain.match(self.member_cfgs, self.cfg.pretrained))

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

    def templates(self, stage: str):
        """The members' agents as a checkpoint of ``stage`` holds them (for loading it)."""
        d = self.d_offline
        return population.stack([stages.agent_template(c, stage, d.obs_dim, d.action_dim, c.seed) for c in self.member_cfgs])

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
            "failed": {str(i): member.error for i, member in enumerate(self.members) if member.error},
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

    def write_summary(self, status: str, error: str | None = None) -> None:
        """Every member's summary.json (and a population's population.json)."""
        seconds = self.stage_seconds()
        out = [summary.write_member_summary(m, status, seconds, error, self.population) for m in self.members]
        if self.population is not None:
            summary.write_population_file(self.root, self.cfg, self.member_cfgs, status, [s["status"] for s in out],
                                          seconds, error)


# ---------------------------------------------------------------------------- the stages
# What runs each stage (made from the run context; ``train(agents, resume)``), in the method's order.
STAGES = {"pretrain": stages.Pretrain, "warmup": stages.Warmup, "boto": stages.Boto, "finetune": stages.Finetune}


# ---------------------------------------------------------------------------- the run
def execute(cfg: RunConfig, member_cfgs: list[RunConfig], root: Path, member_runs: list[RunDir],
            d_offline_raw: Dataset, *, resume: bool = False) -> list[dict[str, Any]]:
    """Train the members (configs that differ in seed and alpha only) as one population whose
    checkpoints are in ``root`` (a single run: one member, whose run directory is ``root``);
    returns every member's summary."""
    spec, method, root = get_task(cfg.task), get_method(cfg.method), Path(root)
    root.mkdir(parents=True, exist_ok=True)
    d_offline = transform_dataset(cfg, spec, d_offline_raw)
    ckpt = CheckpointManager(RunDir(root).checkpoints)
    latest, state, failed, mid = resume_point(ckpt, member_cfgs, resume)
    wandb_runs = tracking.start(member_cfgs, member_runs)  # one W&B run per member (None: no --wandb)
    members = [MemberRun(c, r, w, failed.get(str(i)))
               for i, (c, r, w) in enumerate(zip(member_cfgs, member_runs, wandb_runs))]
    ctx = RunContext(cfg, spec, root, members, d_offline, state)
    for member in members:
        member.truncate_logs(method.stages, mid, state["done_stages"])
    if latest is not None:
        where = f"{mid['stage']} step {mid['step']}" if mid else f"the end of {state['done_stages'][-1]}"
        print(f"botorl: resuming {root} from {where} (checkpoint {latest['name']})", file=sys.stderr)
    ctx.write_summary("running")

    agents = None
    try:
        # SIGTERM / SIGINT: the stages stop at a step with a checkpoint; every matmul at the
        # config's precision (traced inside, so every jitted call of the stages follows it)
        with preempt.deferred(), matmul_precision(cfg.precision):
            if state["done_stages"]:
                last = state["done_stages"][-1]
                agents = ctx.load_agents(checkpoint_name(last, None), ctx.templates(last))
            if "warmup" in state["done_stages"]:
                ctx.d_warmups = _load_warmups(ckpt, ctx.warmup_keys())
            for stage in method.stages:
                if stage in state["done_stages"]:
                    continue
                if preempt.requested():  # between two stages: the last one's final checkpoint is the point
                    raise preempt.interrupted()
                ctx.begin_stage(stage)
                at = ctx.contents(mid) if mid is not None and mid["stage"] == stage else None  # its mid-stage point
                run = STAGES[stage](ctx)
                agents = run.train(agents, at)
                ctx.end_stage()
                state["done_stages"].append(stage)
                ctx.save(stage, None, agents, run.end)
    except BaseException as err:  # a signal, a divergence, a Ctrl-C or a bug: the run can be resumed
        ctx.end_stage()
        if isinstance(err, Interrupted):
            ctx.write_summary("interrupted")
        elif isinstance(err, TrainingDivergedError):
            ctx.write_summary("failed", error=str(err))
            summary.plot_curves(members)
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
    summaries = [summary.read_summary(member.run) for member in members]
    summary.plot_curves(members)
    ctx.close()
    tracking.finish(wandb_runs)
    return summaries


def _load_warmups(ckpt: CheckpointManager, keys: list[str]) -> list[Dataset] | None:
    saved = [ckpt.arrays(checkpoint_name("warmup", None), key) for key in keys]
    if not all(saved):
        return None
    return [Dataset(**{k: a.get(k) for k in FIELDS}, metadata={"source": "D_warmup (checkpoint)"}) for a in saved]

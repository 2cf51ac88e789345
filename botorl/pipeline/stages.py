"""The four stages of a run. Each is a function from explicit inputs to its outputs.

    pretrain(cfg, member_cfgs, d, hooks)               -> agents     Cal-QL / CQL / IQL on D_offline
    warmup(cfg, member_cfgs, spec, agents, ...)         -> D_warmups  frozen policy, stochastic actions, no updates
    boto(cfg, member_cfgs, agents, d, d_warmups, hooks) -> agents     BOTO critic training on D_offline u D_warmup
    finetune(cfg, member_cfgs, method, agents, loop, hooks) -> agents online learning (WSRL / continued / scratch)

A stage reads no run context: it takes the data, the members' configs (their streams:
``Streams.of``), the agents, the method, and for the online stages the ``OnlineState`` (its envs,
buffer and generators), plus ``Hooks``, the narrow callbacks by which it logs, checks,
evaluates, shows progress and hands a mid-stage checkpoint's contents (agents and a state dict)
to the runner, which does every checkpoint read and write (runner.py) and gives a resumed
stage the checkpoint's contents as ``resume``.

Every stage runs a population (a single run is one of one): ``agents`` are the members'
agents stacked on a leading axis, and every update, policy call and evaluation is one jitted
call for all; each member's streams are seeded by its own seed only (docs/populations.md).
Log, checkpoint and evaluation points follow from the step alone (``Schedule``), and a
checkpoint holds everything that decides a stage's future, so a stage given ``resume``
continues exactly (docs/reliability.md).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, replace
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from botorl.agents import population  # by module: a test swaps its functions to count calls
from botorl.agents.common import jit_q_mean
from botorl.agents.cql import CQLAgent
from botorl.agents.iql import IQLAgent
from botorl.agents.sac import SACAgent
from botorl.boto.phase import boto_updates
from botorl.configs.members import Streams
from botorl.configs.methods import get_method
from botorl.data.dataset import Dataset, RewardTransform
from botorl.data.replay import ReplayBuffer
from botorl.pipeline import faults, preempt
from botorl.pipeline.online import OnlineState, rng_from

STAGES = ("pretrain", "warmup", "boto", "finetune")


@dataclass(frozen=True)
class Hooks:
    """What a stage reports to its run (the runner's ``RunContext`` gives them): ``log(stage,
    step, rows)`` and ``check(stage, step, metrics)`` (one item per member; check may raise),
    ``bar(total, initial, desc, unit=...)`` a progress bar, ``evaluate(agents, env_step)`` ->
    rows and ``log_evaluation(rows, env_step)`` (an earlier evaluation of unchanged policies
    logged again), and ``save(stage, step, agents, state)``: a mid-stage checkpoint of the
    agents and the stage's state dict (step, np_rng, extra, arrays, documents)."""

    log: Callable
    check: Callable
    bar: Callable
    evaluate: Callable
    log_evaluation: Callable
    save: Callable


# ---------------------------------------------------------------------------- agents
def make_pretrain_agent(cfg, obs_dim: int, action_dim: int, seed: int):
    if cfg.pretrain == "iql":
        return IQLAgent.create(cfg.offline.iql, obs_dim, action_dim, seed)
    return CQLAgent.create(cfg.offline.cql, obs_dim, action_dim, seed)


def continued_learner(cfg, agents):
    """The pre-trained agent(s) as a "continue" method fine-tunes them: its own loss at the run's
    UTD. Pre-training took one batch per critic step (configs/resolve.py); online, an update
    splits its utd x B rows into utd critic minibatches (IQL's layout is per update instead)."""
    if not hasattr(agents.config, "utd_ratio"):
        return agents
    return agents.replace(config=replace(agents.config, utd_ratio=cfg.online.utd))


def agent_template(cfg, stage: str, obs_dim: int, action_dim: int, seed: int):
    """An agent with the structure a checkpoint of ``stage`` holds (for loading it): the
    fine-tuning learner in fine-tuning, the pre-training agent before."""
    if stage != "finetune":
        return make_pretrain_agent(cfg, obs_dim, action_dim, seed)
    if get_method(cfg.method).finetune_start == "continue":
        return continued_learner(cfg, make_pretrain_agent(cfg, obs_dim, action_dim, seed))
    return SACAgent.create(cfg.online.sac, obs_dim, action_dim, seed)


def start_finetuning(cfg, member_cfgs, method, agents, action_dim: int, probe_observations: np.ndarray):
    """The fine-tuning learners, as the method starts them (``Method.finetune_start``)."""
    oc, start = cfg.online, method.finetune_start
    if start == "warm_start":
        # WSRL's warm start: SAC (10 critics) from the pre-trained (or BOTO-trained) networks.
        # From IQL (no temperature) the initial one comes from the probe states (agents/temperature.py).
        return population.stack([SACAgent.from_pretrained(population.member_of(agents, i), oc.sac,
                                                          seed=Streams.of(c).warm_start, observations=probe_observations)
                                 for i, c in enumerate(member_cfgs)])
    if start == "scratch":
        return population.stack([SACAgent.create(oc.sac, probe_observations.shape[1], action_dim, Streams.of(c).scratch)
                                 for c in member_cfgs])
    return continued_learner(cfg, agents)  # "continue": the pre-trained agent keeps its own loss


def q_fn(agent):
    """Q(s, a) averaged over one agent's critic ensemble, on host arrays (for QProbe)."""
    return lambda o, a: np.asarray(jit_q_mean(agent, jnp.asarray(o), jnp.asarray(a)))


# ---------------------------------------------------------------------------- the loop's pieces
@dataclass(frozen=True)
class Points:
    log: bool
    checkpoint: bool
    evaluate: bool = False


@dataclass(frozen=True)
class Schedule:
    """A stage's log, checkpoint and evaluation points, from the step alone (so a resumed stage
    keeps them); the stage end's checkpoint is the runner's."""

    total: int
    log_every: int
    checkpoint_every: int
    evaluate: Callable[[int], bool] | None = None

    def __call__(self, prev: int, step: int) -> Points:
        return Points(log=step // self.log_every > prev // self.log_every or step == self.total,
                      checkpoint=step // self.checkpoint_every > prev // self.checkpoint_every and step < self.total,
                      evaluate=self.evaluate is not None and self.evaluate(step))


class Window:
    """Each member's metrics between two log points: ``flush`` gives, per member, the mean of
    each scalar metric over the updates it took part in (one host transfer)."""

    def __init__(self, n: int):
        self.n, self.rows = n, []

    def add(self, metrics, active=None) -> None:
        self.rows.append((metrics, np.ones(self.n, bool) if active is None else np.asarray(active)))

    def state_dict(self) -> dict[str, np.ndarray] | None:
        """The rows since the last flush (None: none), for the checkpoint an interrupt writes
        between two log points (periodic ones come after a flush)."""
        if not self.rows:
            return None
        host = jax.device_get([w for w, _ in self.rows])
        keys = [k for k, v in host[0].items() if np.asarray(v).ndim == 1]
        out = {f"m.{k}": np.stack([np.asarray(h[k]) for h in host]) for k in keys}
        out["mask"] = np.stack([m for _, m in self.rows])
        return out

    def load(self, arrays: dict[str, np.ndarray] | None) -> None:
        if arrays:
            keys = [k[2:] for k in arrays if k.startswith("m.")]
            self.rows = [({k: arrays[f"m.{k}"][t] for k in keys}, arrays["mask"][t]) for t in range(len(arrays["mask"]))]

    def flush(self) -> list[dict[str, float]]:
        rows, self.rows = self.rows, []
        if not rows:
            return [{} for _ in range(self.n)]
        host = jax.device_get([w for w, _ in rows])
        masks = np.stack([m for _, m in rows])  # (T, N)
        keys = [k for k, v in host[0].items() if np.asarray(v).ndim == 1]
        out = []
        for i in range(self.n):
            t = np.flatnonzero(masks[:, i])
            out.append({k: float(np.mean([np.asarray(host[j][k])[i] for j in t])) for k in keys} if len(t) else {})
        return out


class Rate:
    """Steps per second between two calls (logged; no part of the resumable state)."""

    def __init__(self, step: int):
        self.t, self.step = time.perf_counter(), step

    def __call__(self, step: int) -> float:
        now = time.perf_counter()
        rate = (step - self.step) / max(now - self.t, 1e-9)
        self.t, self.step = now, step
        return rate


def step_end(stage: str, step: int, total: int, due: Points, save: Callable[[bool], None]) -> None:
    """What ends every step of a stage: the scheduled checkpoint (``save(False)``), the
    fault-injection point, and after a SIGTERM / SIGINT the checkpoint of this very step
    (``save(True)``: with the metrics window; never twice) and ``Interrupted``."""
    if due.checkpoint:
        save(False)
    faults.step(stage, step)
    if step < total and preempt.requested():
        if not due.checkpoint:
            save(True)
        raise preempt.interrupted()


def pretrain_groups(member_cfgs) -> tuple[list[int], list[int]]:
    """(the first member of each seed, each member's index into that list)."""
    first: dict[int, int] = {}
    group = [first.setdefault(c.seed, len(first)) for c in member_cfgs]
    return [group.index(g) for g in range(len(first))], group


def offline_loop(agents, update: Callable, chunk: Callable[[int], int], step: int, schedule: Schedule,
                 window: Window, bar, *, stage: str, check: Callable, log: Callable, save: Callable,
                 check_every_call: bool = False):
    """The offline stages' loop (pre-training, BOTO; d3rlpy's one fitter is the model): from
    ``step`` to ``schedule.total``, ``update(agents, step, k)`` -> (agents, metrics) runs k =
    ``chunk(step)`` updates in one jitted call; at log and checkpoint points (at every call
    with ``check_every_call``) the window's means are checked (``check(step, ms)``, which may
    raise) and at log points logged (``log(step, ms)``); then ``step_end`` with
    ``save(step, agents, interrupted)``. Returns the agents."""
    while step < schedule.total:
        k = chunk(step)
        agents, metrics = update(agents, step, k)
        window.add(metrics)
        prev, step = step, step + k
        bar.update(k)
        due = schedule(prev, step)
        if due.log or due.checkpoint or check_every_call:
            ms = window.flush()
            check(step, ms)
            if due.log:
                log(step, ms)
        step_end(stage, step, schedule.total, due, lambda interrupted: save(step, agents, interrupted))
    return agents


# ---------------------------------------------------------------------------- stage 1
def pretrain(cfg, member_cfgs, d: Dataset, hooks: Hooks, resume: dict | None = None):
    """Offline pre-training with the configured algorithm on the transformed D_offline ``d``
    (held once; each member samples its own batches)."""
    oc, n = cfg.offline, len(member_cfgs)
    # Members of one seed differ only in BOTO's alpha, which pre-training does not read: they
    # share one pre-training (computed once, by the first of them; mid-stage checkpoints hold
    # one agent per seed) and each gets its copy at the end.
    reps, group = pretrain_groups(member_cfgs)
    streams = [Streams.of(member_cfgs[r]) for r in reps]
    agents = population.stack([make_pretrain_agent(member_cfgs[r], d.obs_dim, d.action_dim, s.pretrain)
                               for r, s in zip(reps, streams)])
    step, states = 0, [None] * len(reps)
    if resume is not None:
        agents = resume["agents"](agents)
        step, states = int(resume["step"]), resume.get("np_rng")
        states = states if isinstance(states, list) else [states] * len(reps)
    rngs = [rng_from(st, s.pretrain_batches) for s, st in zip(streams, states)]
    on_device = jax.default_backend() != "cpu" if oc.sample_on_device is None else oc.sample_on_device
    if on_device:
        arrays = d.to_device()
        # the key of each call follows from (seed, step), so a resumed run draws the same batches
        base_keys = [jax.random.PRNGKey(s.pretrain_keys) for s in streams]

        def update(agents, step: int, k: int):
            keys = jnp.stack([jax.random.fold_in(bk, step) for bk in base_keys])
            return population.update_many_on_device(agents, arrays, keys, k, oc.batch_size)
    else:
        def update(agents, step: int, k: int):
            return population.update_many(agents, d.sample_members(rngs, oc.batch_size, k))

    window, rate = Window(len(reps)), Rate(step)
    if resume is not None:
        window.load(resume["arrays"].get("window"))
    shared = f" x {len(reps)} seeds for {n} members" if len(reps) < n else f" x {n} members"

    def log(step: int, per_seed: list[dict]) -> None:
        ms, steps_per_s = [per_seed[g] for g in group], rate(step)
        hooks.log("pretrain", step, [{**m, "steps_per_s": steps_per_s} for m in ms])
        bar.set_postfix(loss=f"{ms[0].get('critic_loss', float('nan')):.3g}", q=f"{ms[0].get('q_data', float('nan')):.3g}")

    def save(step: int, agents, interrupted: bool) -> None:
        w = window.state_dict() if interrupted else None
        hooks.save("pretrain", step, agents, {"np_rng": [r.bit_generator.state for r in rngs],
                                              "arrays": {"window": w} if w else None})

    with hooks.bar(oc.steps, step, f"pretrain ({cfg.pretrain})" + (shared if n > 1 else "")) as bar:
        # a call ends at the next checkpoint boundary so that checkpoints land on multiples
        agents = offline_loop(
            agents, update, lambda s: min(oc.updates_per_call, oc.steps - s, cfg.checkpoint_every - s % cfg.checkpoint_every),
            step, Schedule(oc.steps, oc.log_every, cfg.checkpoint_every), window, bar, stage="pretrain",
            check=lambda step, per_seed: hooks.check("pretrain", step, [per_seed[g] for g in group]), log=log, save=save)
    if len(reps) < n:
        agents = jax.tree_util.tree_map(lambda x: x[np.asarray(group)], agents)
    return agents


# ---------------------------------------------------------------------------- stage 2a
def _reseed_online(member_cfgs, agents):
    """The pre-trained agents' keys, folded with ``online_reseed`` for the members that set it,
    so their warm-up (and BOTO) draws differ from the runs they share the pre-training with."""
    reseeds = [c.online_reseed for c in member_cfgs]
    if not any(reseeds):
        return agents
    keys = [jax.random.fold_in(population.member_of(agents, i).rng, k) if k else population.member_of(agents, i).rng
            for i, k in enumerate(reseeds)]
    # the new keys where the networks are (else the first policy call copies them there)
    where = jax.tree_util.tree_leaves(agents.actor.params)[0].sharding
    return agents.replace(rng=jax.device_put(jnp.stack(keys), where))


def warmup(cfg, member_cfgs, spec, agents, transform: Callable[[Dataset], Dataset],
           hooks: Hooks) -> tuple[list[Dataset] | None, Any]:
    """D_warmup: ``warmup.steps`` env steps of the frozen pre-trained policy (stochastic), one
    env per member. These are the first online env steps (WSRL's accounting); the frozen
    policy's step-0 evaluation is logged again at each evaluation point the warm-up passes.
    No mid-stage checkpoint: a resume runs it again, which gives the same D_warmup."""
    n, N = cfg.warmup.steps, len(member_cfgs)
    if n == 0:
        return None, agents
    seeds = [Streams.of(c).warmup_env for c in member_cfgs]
    envs = [spec.make_env(seed=s) for s in seeds]
    obs = np.stack([np.asarray(e.reset(seed=s)[0], np.float32) for e, s in zip(envs, seeds)])
    agents = _reseed_online(member_cfgs, agents)
    O, A = spec.obs_dim, spec.action_dim
    rows = {"observations": np.zeros((N, n, O), np.float32), "actions": np.zeros((N, n, A), np.float32),
            "rewards": np.zeros((N, n), np.float32), "next_observations": np.zeros((N, n, O), np.float32),
            "terminals": np.zeros((N, n), bool), "episode_ends": np.zeros((N, n), bool)}
    successes: list[list[float]] = [[] for _ in range(N)]
    ep_success = np.zeros(N)
    first_eval = None
    try:
        with hooks.bar(n, 0, "warm-up (frozen policy)", unit="env step") as bar:
            for t in range(n):
                if t % cfg.eval.interval == 0:
                    first_eval = hooks.evaluate(agents, t) if first_eval is None else hooks.log_evaluation(first_eval, t)
                actions, agents = population.sample(agents, obs)
                actions = np.asarray(jax.device_get(actions), dtype=np.float32)
                for i, env in enumerate(envs):
                    next_obs, r, terminated, truncated, info = env.step(actions[i])
                    ep_success[i] = max(ep_success[i], float(info.get("success", 0.0)))
                    for k, v in zip(rows, (obs[i], actions[i], r, next_obs, terminated, terminated or truncated)):
                        rows[k][i, t] = v
                    obs[i] = next_obs
                    if terminated or truncated:
                        successes[i].append(ep_success[i])
                        ep_success[i] = 0.0
                        obs[i] = env.reset()[0]
                if t % 200 == 0:
                    bar.update(min(200, n - bar.n))
                faults.step("warmup", t + 1)
                if preempt.requested():  # the resume starts the warm-up again (exact; see the docstring)
                    raise preempt.interrupted()
            bar.update(n - bar.n)
    finally:
        for env in envs:
            env.close()
    d_warmups = [transform(Dataset(**{k: v[i] for k, v in rows.items()},
                                   metadata={"source": f"D_warmup ({n} steps of the pre-trained policy)"}))
                 for i in range(N)]
    hooks.log("warmup", n, [{"episodes": len(s), "success_rate": float(np.mean(s)) if s else float("nan"),
                             "reward_mean": float(np.mean(rows["rewards"][i]))} for i, s in enumerate(successes)])
    return d_warmups, agents


# ---------------------------------------------------------------------------- stage 2b
def boto(cfg, member_cfgs, agents, d: Dataset, d_warmups: list[Dataset] | None, hooks: Hooks,
         resume: dict | None = None):
    """BOTO critic training on D_offline u D_warmup, each member with its own alpha and
    D_warmup (botorl.boto.phase.boto_updates in the offline loop, with this run's logs and
    checkpoints)."""
    bc, n, start = cfg.boto, len(member_cfgs), 0
    if resume is not None:
        agents, start = resume["agents"](agents), int(resume["step"])
    alphas = [c.alpha for c in member_cfgs]
    update = boto_updates(agents, d, d_warmups or [None] * n, bc, alphas, [Streams.of(c).boto for c in member_cfgs])
    t0 = time.perf_counter()

    def log(step: int, ms: list[dict]) -> None:
        hooks.log("boto", step, [{"seconds": time.perf_counter() - t0, **m} for m in ms])
        bar.set_postfix(loss=f"{ms[0]['critic_loss']:.3g}", q_data=f"{ms[0]['q_data']:.3g}")

    label = f"BOTO alpha={alphas[0]:+.2f}" if n == 1 else f"BOTO x {n} members"
    with hooks.bar(bc.boto_steps, start, label) as bar:
        # the batches of a call follow from its index (boto_updates): no generator state to save,
        # and calls are not cut at checkpoint points (train_boto's calls, so its numbers); the
        # metrics are checked after every call, and a log point logs its call's
        return offline_loop(agents, update, lambda s: min(bc.steps_per_call, bc.boto_steps - s), start,
                            Schedule(bc.boto_steps, max(cfg.offline.log_every, bc.steps_per_call), cfg.checkpoint_every),
                            Window(n), bar, stage="boto", check=lambda step, ms: hooks.check("boto", step, ms),
                            log=log, save=lambda step, agents, interrupted: hooks.save("boto", step, agents, {}),
                            check_every_call=True)


# ---------------------------------------------------------------------------- stage 3
def online_state(cfg, member_cfgs, method, spec, d: Dataset, mc_returns: Callable[[Dataset], np.ndarray],
                 d_warmups: list[Dataset] | None) -> OnlineState:
    """The online loop at its start, from its inputs: one env per member (``Streams.online_env``)
    at its first reset, a member buffer (holding D_warmup for WSRL's warm start), each member's
    batch generator (``Streams.online_batches``), the online config, the method and the task's
    reward transform; the step after the warm-up."""
    oc, streams = cfg.online, [Streams.of(c) for c in member_cfgs]
    n_warm = len(d_warmups[0]) if d_warmups is not None else 0
    buffer = ReplayBuffer(oc.buffer_capacity or (oc.steps + n_warm + 1), d.obs_dim, d.action_dim, members=len(streams))
    if d_warmups is not None and method.finetune_start == "warm_start":
        buffer.insert_dataset(d_warmups)  # WSRL: the online buffer starts with D_warmup
    state = OnlineState([spec.make_env(seed=s.online_env) for s in streams], buffer,
                        [rng_from(None, s.online_batches) for s in streams], oc, method, RewardTransform.of(spec),
                        mc_returns=mc_returns, success_mode=spec.success_mode, offline=d, step=n_warm)
    state.reset([s.online_env for s in streams])
    return state


def resume_online(state: OnlineState, resume: dict, member_cfgs) -> None:
    """``state`` as the checkpoint ``resume`` saved it; one written before env states were saved
    starts new episodes, with seeds not used before (the run is then not exact)."""
    if not state.load_state_dict(resume):
        print("botorl: warning: this checkpoint has no env state (written by an older botorl); fine-tuning "
              "continues with new episodes, so the run will not repeat an uninterrupted one exactly.",
              file=sys.stderr)
        state.reset([Streams.of(c).online_env + 100_003 * state.resumes for c in member_cfgs])


def finetune(cfg, member_cfgs, method, agents, state: OnlineState, probe_observations: np.ndarray, hooks: Hooks,
             resume: dict | None = None):
    """Online learning with ``state`` (online_state) from the step after the warm-up to
    ``online.steps`` (the warm-up's env steps counted, as WSRL), evaluating at its start, at
    ``eval.due`` points and at the end; what decides the future besides the agents is ``state``."""
    oc, n = cfg.online, len(member_cfgs)
    agents = start_finetuning(cfg, member_cfgs, method, agents, state.buffer.action_dim, probe_observations)
    if resume is not None:
        resume_online(state, resume, member_cfgs)
        agents = resume["agents"](agents)
    # where the updates keep them (a population's members split over the CPU devices), from the
    # first step on: a resumed run's loaded agents sit on one device, where the policy call
    # compiles another program than the uninterrupted run's at that step (its actions differed
    # in the last bit, and the run drifted from there)
    agents = population.placed(agents, every_leaf=True)[0]
    points = Schedule(oc.steps, oc.log_every, cfg.checkpoint_every,
                      evaluate=lambda step: cfg.eval.due(step, oc.steps, cfg.warmup.steps))
    if state.step == state.start and state.last_eval < state.start:
        hooks.evaluate(agents, state.start)
        state.last_eval = state.start
    window, rate = Window(n), Rate(state.step)
    if resume is not None:
        window.load(resume["arrays"].get("window"))

    def save(interrupted: bool) -> None:
        sd = state.state_dict()
        w = window.state_dict() if interrupted else None
        if w:
            sd["arrays"]["window"] = w
        hooks.save("finetune", state.step, agents, sd)

    label = f"fine-tune ({cfg.method})" + (f" x {n} members" if n > 1 else "")
    with state, hooks.bar(oc.steps, state.step, label, unit="env step") as bar:
        while state.step < oc.steps:
            agents = state.advance(agents, window)  # act, step the envs, store; one UTD update
            bar.update(1)
            due = points(state.step - 1, state.step)
            if due.log or due.checkpoint:
                ms = window.flush()
                hooks.check("finetune", state.step, ms)
                if due.log:
                    hooks.log("finetune", state.step, state.log_rows(ms, rate(state.step)))
            if due.evaluate:
                rows = hooks.evaluate(agents, state.step)
                state.last_eval = state.step
                bar.set_postfix(success=f"{rows[0]['success']:.2f}")
            step_end("finetune", state.step, oc.steps, due, save)
    return agents

"""The four stages of a run (``pretrain``, ``warmup``, ``boto``, ``finetune``; their inputs and
outputs: docs/architecture.md), each a function from explicit inputs to its outputs.

Every stage runs ``stage_loop``; the warm-up and fine-tuning run it over one online loop state
(``OnlineState``). A stage reads no run context: it gets ``Hooks``, its callbacks into the
runner, which does every checkpoint read and write and hands a resumed stage the checkpoint's
contents as ``resume``. ``agents`` are a population's agents stacked on a leading axis (a single
run is one of one), each member's streams seeded by its own seed only (docs/populations.md). Log,
checkpoint and evaluation points follow from the step alone (``Schedule``), so a stage given
``resume`` continues exactly (docs/reliability.md).
"""

from __future__ import annotations

import time
from collections import namedtuple
from dataclasses import dataclass
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from botorl.agents import population  # by module: a test swaps its functions to count calls
from botorl.agents.common import jit_agent_q_mean
from botorl.agents.cql import CQLAgent
from botorl.agents.iql import IQLAgent
from botorl.agents.sac import SACAgent
from botorl.boto.phase import boto_updates
from botorl.configs.members import Streams
from botorl.configs.methods import get_method
from botorl.data.dataset import Dataset, RewardTransform
from botorl.data.replay import ReplayBuffer
from botorl.pipeline import faults, preempt
from botorl.pipeline.online import OnlineState

# A stage's callbacks into its run (runner.RunContext's): ``log`` and ``check`` (stage, step, one
# item per member; check may raise), ``bar`` (a progress bar), ``evaluate(agents, step)`` -> rows,
# ``log_evaluation(rows, step)`` (unchanged policies' rows again), and ``save(stage, step, agents,
# state_dict)`` (step None: the stage's end).
Hooks = namedtuple("Hooks", "log check bar evaluate log_evaluation save")


# ---------------------------------------------------------------------------- agents
def make_pretrain_agent(cfg, obs_dim: int, action_dim: int, seed: int):
    if cfg.pretrain == "iql":
        return IQLAgent.create(cfg.offline.iql, obs_dim, action_dim, seed)
    return CQLAgent.create(cfg.offline.cql, obs_dim, action_dim, seed)


def agent_template(cfg, stage: str, obs_dim: int, action_dim: int, seed: int):
    """An agent with the structure a checkpoint of ``stage`` holds (for loading it): the
    fine-tuning learner in fine-tuning, the pre-training agent before."""
    if stage != "finetune" or get_method(cfg.method).finetune_start == "continue":
        return make_pretrain_agent(cfg, obs_dim, action_dim, seed)
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
    # "continue": the pre-trained agent keeps its own loss, at the online UTD its batches carry
    return agents


def q_fn(agent):
    """Q(s, a) averaged over one agent's critic ensemble, on host arrays (for QProbe)."""
    return lambda o, a: np.asarray(jit_agent_q_mean(agent, jnp.asarray(o), jnp.asarray(a)))


# ---------------------------------------------------------------------------- the loop's pieces
Points = namedtuple("Points", "log checkpoint evaluate")  # what is due at a step


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
        arrays, self.rows = self.state_dict(), []
        if arrays is None:
            return [{} for _ in range(self.n)]
        mask, keys = arrays["mask"], [k for k in arrays if k.startswith("m.")]  # mask: (T, N)
        return [{k[2:]: float(np.mean(arrays[k][mask[:, i], i])) for k in keys} if mask[:, i].any() else {}
                for i in range(self.n)]


class Rate:
    """Steps per second between two calls (logged; no part of the resumable state)."""

    def __init__(self, step: int):
        self.t, self.step = time.perf_counter(), step

    def __call__(self, step: int) -> float:
        now = time.perf_counter()
        rate = (step - self.step) / max(now - self.t, 1e-9)
        self.t, self.step = now, step
        return rate


def pretrain_groups(member_cfgs) -> tuple[list[int], list[int]]:
    """(the first member of each seed, each member's index into that list)."""
    first: dict[int, int] = {}
    group = [first.setdefault(c.seed, len(first)) for c in member_cfgs]
    return [group.index(g) for g in range(len(first))], group


def stage_loop(agents, update: Callable, chunk: Callable[[int], int], step: int, schedule: Schedule,
               window: Window, bar, *, stage: str, check: Callable, log: Callable, save: Callable,
               evaluate: Callable | None = None, check_every_call: bool = False):
    """Every stage's loop, from ``step`` to ``schedule.total``: ``update(agents, step, k)`` ->
    (agents, metrics or None: the update added its own) runs k = ``chunk(step)`` updates in one
    jitted call (the offline stages) or one online step; the window's means are checked (``check``
    may raise; at every call with ``check_every_call``) and logged, the agents evaluated and saved
    (``save(step, agents, False)``) at the schedule's points. After a SIGTERM / SIGINT: the
    checkpoint of this very step (``interrupted`` True: with the metrics window), then
    ``Interrupted``. Returns the agents."""
    while step < schedule.total:
        k = chunk(step)
        agents, metrics = update(agents, step, k)
        if metrics is not None:
            window.add(metrics)
        prev, step = step, step + k
        bar.update(k)
        due = schedule(prev, step)
        if due.log or due.checkpoint or check_every_call:
            ms = window.flush()
            check(step, ms)
            if due.log:
                log(step, ms)
        if due.evaluate:
            evaluate(agents, step)
        if due.checkpoint:
            save(step, agents, False)
        faults.step(stage, step)
        if step < schedule.total and preempt.requested():
            if not due.checkpoint:
                save(step, agents, True)
            raise preempt.interrupted()
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
    rngs, step, window = [np.random.default_rng(s.pretrain_batches) for s in streams], 0, Window(len(reps))
    if resume is not None:
        agents = resume["agents"](agents)
        step, states = int(resume["step"]), resume.get("np_rng")
        for rng, st in zip(rngs, states if isinstance(states, list) else [states] * len(reps)):
            if st is not None:  # as saved; else from its seed
                rng.bit_generator.state = st
        window.load(resume["arrays"].get("window"))
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

    rate = Rate(step)
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
        agents = stage_loop(
            agents, update, lambda s: min(oc.updates_per_call, oc.steps - s, cfg.checkpoint_every - s % cfg.checkpoint_every),
            step, Schedule(oc.steps, oc.log_every, cfg.checkpoint_every), window, bar, stage="pretrain",
            check=lambda step, per_seed: hooks.check("pretrain", step, [per_seed[g] for g in group]), log=log, save=save)
    if len(reps) < n:
        agents = jax.tree_util.tree_map(lambda x: x[np.asarray(group)], agents)
    return agents


# ---------------------------------------------------------------------------- the online loop
def online_state(cfg, member_cfgs, method, spec, offline: Dataset | None, mc_returns: Callable | None) -> OnlineState:
    """The online loop at step 0, from its inputs: one env per member (``Streams.online_env``;
    the warm-up's and fine-tuning's, one loop) at its first reset, a member buffer for every
    online step, each member's batch generator (``Streams.online_batches``), the online config,
    the method and the task's reward transform (``botorl bench`` builds its loop here too)."""
    oc, streams = cfg.online, [Streams.of(c) for c in member_cfgs]
    buffer = ReplayBuffer(oc.buffer_capacity or (oc.steps + 1), spec.obs_dim, spec.action_dim, members=len(streams))
    state = OnlineState([spec.make_env(seed=s.online_env) for s in streams], buffer,
                        [np.random.default_rng(s.online_batches) for s in streams], oc, method, RewardTransform.of(spec),
                        mc_returns=mc_returns, success_mode=spec.success_mode, offline=offline)
    state.reset([s.online_env for s in streams])
    return state


def online_loop(state: OnlineState, agents, schedule: Schedule, window: Window, bar, **kw):
    """``stage_loop`` over the online loop ``state``: one ``state.advance`` a step (act, step the
    envs, store; one UTD update while ``state.learning``), as WSRL's finetune.py, whose warm-up
    is this loop with learning off."""
    return stage_loop(agents, lambda agents, step, k: (state.advance(agents, window), None), lambda step: 1,
                      state.step, schedule, window, bar, **kw)


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


def warmup(cfg, member_cfgs, agents, state: OnlineState, hooks: Hooks) -> tuple[list[Dataset] | None, Any]:
    """D_warmup: the online loop ``state`` (at step 0) for ``warmup.steps`` env steps with learning
    off, as WSRL's finetune.py: the frozen pre-trained policy acts (stochastic), nothing updates.
    These are the first online steps: fine-tuning goes on with the same loop. The frozen policy's
    step-0 evaluation is logged again at each evaluation point passed. D_warmup is each member's
    buffer rows, MC returns by the loop's rule (``state.mc_returns``). No mid-stage checkpoint: a
    resume runs it again from the pre-training's end (the same D_warmup)."""
    n, N = cfg.warmup.steps, len(member_cfgs)
    if n == 0:
        return None, agents
    agents = _reseed_online(member_cfgs, agents)
    first = hooks.evaluate(agents, state.step)
    state.learning, state.ended = False, [[] for _ in range(N)]
    with hooks.bar(n, 0, "warm-up (frozen policy)", unit="env step") as bar:
        agents = online_loop(
            state, agents, Schedule(n, n, n + 1, evaluate=lambda step: step % cfg.eval.interval == 0 and step < n),
            Window(N), bar, stage="warmup", evaluate=lambda agents, step: hooks.log_evaluation(first, step),
            check=lambda step, ms: None, log=lambda step, ms: None, save=lambda step, agents, interrupted: None)
    ended, state.ended, state.learning = state.ended, None, True
    rows, t = state.buffer.state_dict(), state.reward
    d_warmups = []
    for i, ends in enumerate(ended):
        episode_ends = np.zeros(n, bool)
        episode_ends[ends] = True
        dw = Dataset(*(rows[k][i, :n] for k in ("observations", "actions", "rewards", "next_observations")),
                     rows["dones"][i, :n] > 0.5, episode_ends=episode_ends,
                     metadata={"source": f"D_warmup ({n} steps of the pre-trained policy)"})
        d_warmups.append(dw._replace(mc_returns=state.mc_returns(dw)))
    # the rewards as the env gave them
    hooks.log("warmup", n, [{"episodes": state.episodes[i], "success_rate": float(np.mean(s)) if s else float("nan"),
                             "reward_mean": float((np.mean(rows["rewards"][i, :n]) - t.bias) / t.scale)}
                            for i, s in enumerate(state.recent_success)])
    state.recent_success = [[] for _ in range(N)]  # fine-tuning's train_success: its own episodes
    return d_warmups, agents


# ---------------------------------------------------------------------------- stage 2b
def boto(cfg, member_cfgs, agents, d: Dataset, d_warmups: list[Dataset] | None, hooks: Hooks,
         resume: dict | None = None):
    """BOTO critic training on D_offline u D_warmup, each member with its own alpha and
    D_warmup (botorl.boto.phase.boto_updates in the stage loop, with this run's logs and
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
        return stage_loop(agents, update, lambda s: min(bc.steps_per_call, bc.boto_steps - s), start,
                          Schedule(bc.boto_steps, max(cfg.offline.log_every, bc.steps_per_call), cfg.checkpoint_every),
                          Window(n), bar, stage="boto", check=lambda step, ms: hooks.check("boto", step, ms),
                          log=log, save=lambda step, agents, interrupted: hooks.save("boto", step, agents, {}),
                          check_every_call=True)


# ---------------------------------------------------------------------------- stage 3
def finetune(cfg, member_cfgs, method, agents, state: OnlineState, probe_observations: np.ndarray, hooks: Hooks,
             resume: dict | None = None):
    """Online learning: the online loop ``state`` (online_state; after the warm-up, where it
    left it; resumed, as the runner restored it) from its step to ``online.steps`` (the warm-up's
    env steps counted, as WSRL) with the fine-tuning learners, evaluating at its start, at
    ``eval.due`` points and at the end; what decides the future besides the agents is ``state``.
    Every method with a warm-up starts warm (configs/methods.py), so its buffer keeps D_warmup."""
    oc, n = cfg.online, len(member_cfgs)
    agents = start_finetuning(cfg, member_cfgs, method, agents, state.buffer.action_dim, probe_observations)
    window = Window(n)
    if resume is not None:
        agents = resume["agents"](agents)
        window.load(resume["arrays"].get("window"))
    # where the updates keep them (members split over the CPU devices) from the first step on: on one
    # device, a resumed run's loaded agents would compile another policy program (other last bits)
    agents = population.placed(agents, every_leaf=True)[0]
    if resume is None:  # a checkpoint comes after a step: a resumed fine-tuning is past its start
        hooks.evaluate(agents, state.step)
    rate = Rate(state.step)

    def evaluate(agents, step: int) -> None:
        bar.set_postfix(success=f"{hooks.evaluate(agents, step)[0]['success']:.2f}")

    def save(step: int, agents, interrupted: bool) -> None:
        sd, w = state.state_dict(), window.state_dict() if interrupted else None
        if w:
            sd["arrays"]["window"] = w
        hooks.save("finetune", step, agents, sd)

    label = f"fine-tune ({cfg.method})" + (f" x {n} members" if n > 1 else "")
    with state, hooks.bar(oc.steps, state.step, label, unit="env step") as bar:
        return online_loop(state, agents, Schedule(oc.steps, oc.log_every, cfg.checkpoint_every,
                                                   evaluate=lambda step: cfg.eval.due(step, oc.steps, cfg.warmup.steps)),
                           window, bar, stage="finetune", evaluate=evaluate,
                           check=lambda step, ms: hooks.check("finetune", step, ms),
                           log=lambda step, ms: hooks.log("finetune", step, state.log_rows(ms, rate(step))), save=save)

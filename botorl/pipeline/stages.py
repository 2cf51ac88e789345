"""The four stages of a run (``pretrain``, ``warmup``, ``boto``, ``finetune``; their inputs and
outputs: docs/architecture.md), each a ``Stage``: made from ``run`` (runner.RunContext: the run's
config, members, data and callbacks), ``train(agents, resume)`` gives the stage's agents.

A ``Stage`` says what it does at its schedule's points, and ``stage_loop`` calls it; the warm-up
and fine-tuning run over one online loop state (``OnlineState``). The runner does every
checkpoint read and write and hands a resumed stage the checkpoint's contents as ``resume``;
``end`` is what the stage's end-of-stage checkpoint keeps besides the agents. ``agents`` are a
population's agents stacked on a leading axis (a single run is one of one), each member's streams
seeded by its own seed only (docs/populations.md). Log, checkpoint and evaluation points follow
from the step alone (``Schedule``), so a stage given ``resume`` continues exactly (docs/reliability.md).
"""

from __future__ import annotations

import time
from collections import namedtuple
from dataclasses import dataclass
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from botorl.agents import population  # by module: a test swaps its functions to count calls
from botorl.agents.common import jit_agent_q_mean
from botorl.agents.cql import CQLAgent
from botorl.agents.iql import IQLAgent
from botorl.agents.sac import SACAgent
from botorl.batch import BATCH_KEYS
from botorl.boto.phase import boto_updates
from botorl.configs.members import Streams
from botorl.configs.methods import get_method
from botorl.data.dataset import Dataset, RewardTransform
from botorl.data.replay import ReplayBuffer
from botorl.pipeline import faults, preempt
from botorl.pipeline.online import OnlineState


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


# ---------------------------------------------------------------------------- the loop
class Stage:
    """What a stage does at its schedule's points, which ``stage_loop`` calls. By default it checks,
    logs and saves the agents through ``run``, its callbacks into the run (runner.RunContext:
    ``log`` and ``check`` (stage, step, an item per member), ``evaluate(agents, step)`` -> rows,
    ``log_evaluation(rows, step)``, ``save(stage, step, agents, state_dict)``). A stage whose
    ``Schedule`` has evaluation points has its own ``evaluate(agents, step)``."""

    name = ""
    check_every_call = False  # check after every call, not only at log and checkpoint points
    end = None

    def __init__(self, run, schedule: Schedule, member_cfgs: list | None = None):  # None: every member of run's
        self.cfg, self.run, self.schedule, self.bar = run.cfg, run, schedule, None
        self.member_cfgs = run.member_cfgs if member_cfgs is None else member_cfgs
        self.n, self.window = len(self.member_cfgs), Window(len(self.member_cfgs))

    def chunk(self, step: int) -> int:
        return 1

    def update(self, agents, step: int, k: int):
        """One step of the online loop ``self.state`` (the warm-up's and fine-tuning's): act, step
        the envs, store; one UTD update while ``state.learning``, as WSRL's finetune.py, whose
        warm-up is this loop with learning off. The offline stages update otherwise."""
        return self.state.advance(agents, self.window), None

    def check(self, step: int, ms: list[dict]) -> None:
        self.run.check(self.name, step, ms)

    def log(self, step: int, ms: list[dict]) -> None:
        self.run.log(self.name, step, ms)

    def save(self, step: int, agents, interrupted: bool) -> None:
        self.run.save(self.name, step, agents, {})


def stage_loop(stage: Stage, agents, step: int, desc: str, unit: str = "step"):
    """Every stage's loop, from ``step`` to ``stage.schedule.total`` under a progress bar (``desc``):
    ``stage.update(agents, step, k)`` -> (agents, metrics or None: the update added its own) runs
    k = ``stage.chunk(step)`` updates in one jitted call (the offline stages) or one online step;
    the window's means per member are checked (``check`` may raise; at every call with
    ``check_every_call``) and logged, the agents evaluated and saved (``save(step, agents,
    False)``) at the schedule's points. After a SIGTERM / SIGINT: the checkpoint of this very
    step (``save(step, agents, True)``: with the metrics window), then ``Interrupted``. Returns
    the agents."""
    schedule, window = stage.schedule, stage.window
    with tqdm(total=schedule.total, initial=step, desc=desc, unit=unit, dynamic_ncols=True,
              disable=not stage.cfg.progress, mininterval=1.0, smoothing=0.05) as stage.bar:
        while step < schedule.total:
            k = stage.chunk(step)
            agents, metrics = stage.update(agents, step, k)
            if metrics is not None:
                window.add(metrics)
            prev, step = step, step + k
            stage.bar.update(k)
            due = schedule(prev, step)
            if due.log or due.checkpoint or stage.check_every_call:
                ms = window.flush()
                stage.check(step, ms)
                if due.log:
                    stage.log(step, ms)
            if due.evaluate:
                stage.evaluate(agents, step)
            if due.checkpoint:
                stage.save(step, agents, False)
            faults.step(stage.name, step)
            if step < schedule.total and preempt.requested():
                if not due.checkpoint:
                    stage.save(step, agents, True)
                raise preempt.interrupted()
        return agents


# ---------------------------------------------------------------------------- stage 1
class Pretrain(Stage):
    """Offline pre-training with the configured algorithm on the transformed D_offline ``d``
    (held once; each member samples its own batches). Members of one seed differ only in BOTO's
    alpha, which pre-training does not read: they share one pre-training (computed once, by the
    first of them; mid-stage checkpoints hold one agent per seed) and each gets its copy at the end."""

    name = "pretrain"

    def __init__(self, run):
        cfg, oc, first = run.cfg, run.cfg.offline, {}  # the first member of each seed; each member's index into them
        self.group = [first.setdefault(c.seed, len(first)) for c in run.member_cfgs]
        self.reps = [self.group.index(g) for g in range(len(first))]
        super().__init__(run, Schedule(oc.steps, oc.log_every, cfg.checkpoint_every),
                         [run.member_cfgs[r] for r in self.reps])
        self.d, self.oc, self.streams = run.d_offline, oc, [Streams.of(c) for c in self.member_cfgs]
        self.rngs = [np.random.default_rng(s.pretrain_batches) for s in self.streams]

    def update(self, agents, step: int, k: int):
        if self.arrays is None:
            return population.update_many(agents, self.d.sample_members(self.rngs, self.oc.batch_size, k))
        keys = jnp.stack([jax.random.fold_in(bk, step) for bk in self.base_keys])
        return population.update_many_on_device(agents, self.arrays, keys, k, self.oc.batch_size)

    def chunk(self, step: int) -> int:
        # a call ends at the next checkpoint boundary so that checkpoints land on multiples
        every = self.cfg.checkpoint_every
        return min(self.oc.updates_per_call, self.oc.steps - step, every - step % every)

    def check(self, step: int, per_seed: list[dict]) -> None:
        self.run.check(self.name, step, [per_seed[g] for g in self.group])

    def log(self, step: int, per_seed: list[dict]) -> None:
        ms, steps_per_s = [per_seed[g] for g in self.group], self.rate(step)
        self.run.log(self.name, step, [{**m, "steps_per_s": steps_per_s} for m in ms])
        self.bar.set_postfix(loss=f"{ms[0].get('critic_loss', float('nan')):.3g}",
                             q=f"{ms[0].get('q_data', float('nan')):.3g}")

    def save(self, step: int, agents, interrupted: bool) -> None:
        w = self.window.state_dict() if interrupted else None
        self.run.save(self.name, step, agents, {"np_rng": [r.bit_generator.state for r in self.rngs],
                                                "arrays": {"window": w} if w else None})

    def train(self, agents, resume: dict | None = None):
        """The pre-trained agents of every member: those of the runs ``--pretrained`` names (the same
        numbers, read by the runner: shared_pretrain.py), else trained here (from ``resume``'s
        checkpoint where given)."""
        agents = self.run.load_pretrained() if self.cfg.pretrained is not None else self.pretrain(resume)
        self.run.log_q(self.name, self.oc.steps, agents)
        return agents

    def pretrain(self, resume: dict | None):
        n, reps, oc = len(self.group), len(self.reps), self.oc
        on_device = jax.default_backend() != "cpu" if oc.sample_on_device is None else oc.sample_on_device
        self.arrays = self.d.to_device() if on_device else None  # D_offline on the device, where batches are drawn
        # there the key of each call follows from (seed, step), so a resumed run draws the same batches
        self.base_keys = [jax.random.PRNGKey(s.pretrain_keys) for s in self.streams] if on_device else None
        agents = population.stack([make_pretrain_agent(c, self.d.obs_dim, self.d.action_dim, s.pretrain)
                                   for c, s in zip(self.member_cfgs, self.streams)])
        step = 0
        if resume is not None:
            agents = resume["agents"](agents)
            step, states = int(resume["step"]), resume.get("np_rng")
            for rng, st in zip(self.rngs, states if isinstance(states, list) else [states] * reps):
                if st is not None:  # as saved; else from its seed
                    rng.bit_generator.state = st
            self.window.load(resume["arrays"].get("window"))
        self.rate = Rate(step)
        shared = f" x {reps} seeds for {n} members" if reps < n else f" x {n} members"
        agents = stage_loop(self, agents, step, f"pretrain ({self.cfg.pretrain})" + (shared if n > 1 else ""))
        if reps < n:
            agents = jax.tree_util.tree_map(lambda x: x[np.asarray(self.group)], agents)
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


class Warmup(Stage):
    """D_warmup: the online loop ``state`` (at step 0) for ``warmup.steps`` env steps with learning
    off, as WSRL's finetune.py: the frozen pre-trained policy acts (stochastic), nothing updates.
    These are the first online steps: fine-tuning goes on with the same loop. The frozen policy's
    step-0 evaluation is logged again at each evaluation point passed. D_warmup is each member's
    buffer rows, MC returns by the loop's rule (``state.mc_returns``). Nothing learns, so nothing
    is checked or logged in the loop, and no mid-stage checkpoint: a resume runs it again from
    the pre-training's end (the same D_warmup). The loop ``state`` is the run's (``run.online_loop``),
    made here; D_warmup goes to ``run.d_warmups``, and with the loop's state into ``end``."""

    name = "warmup"

    def __init__(self, run):
        cfg, n = run.cfg, run.cfg.warmup.steps
        super().__init__(run, Schedule(n, n, n + 1, evaluate=lambda step: step % cfg.eval.interval == 0 and step < n))

    check = log = save = lambda self, *args: None  # noqa: E731 - nothing learns: nothing to check, log or keep

    def evaluate(self, agents, step: int) -> None:
        self.run.log_evaluation(self.first, step)

    def train(self, agents, resume: dict | None = None):
        n, N, state = self.cfg.warmup.steps, self.n, self.run.online_loop()
        self.state = state
        if n == 0:
            return agents
        agents = _reseed_online(self.member_cfgs, agents)
        self.first = self.run.evaluate(agents, state.step)
        state.learning, state.ended = False, [[] for _ in range(N)]
        agents = stage_loop(self, agents, state.step, "warm-up (frozen policy)", unit="env step")
        ended, state.ended, state.learning = state.ended, None, True
        rows, t = state.buffer.state_dict(), state.reward
        d_warmups = []
        for i, ends in enumerate(ended):  # ends: the rows where one of member i's episodes ended
            dw = Dataset.of_batch({k: rows[k][i, :n] for k in BATCH_KEYS}, episode_ends=np.isin(np.arange(n), ends),
                                  metadata={"source": f"D_warmup ({n} steps of the pre-trained policy)"})
            d_warmups.append(dw._replace(mc_returns=state.mc_returns(dw)))
        # the rewards as the env gave them
        self.run.log("warmup", n, [{"episodes": state.episodes[i], "success_rate": float(np.mean(s)) if s else float("nan"),
                                    "reward_mean": float((np.mean(rows["rewards"][i, :n]) - t.bias) / t.scale)}
                                   for i, s in enumerate(state.recent_success)])
        state.recent_success = [[] for _ in range(N)]  # fine-tuning's train_success: its own episodes
        self.run.d_warmups, self.end = d_warmups, state.state_dict()  # its end's checkpoint: the loop, and D_warmup
        self.end["arrays"].update({k: dw.arrays() for k, dw in zip(self.run.warmup_keys(), d_warmups)})
        return agents


# ---------------------------------------------------------------------------- stage 2b
class Boto(Stage):
    """BOTO critic training on D_offline u D_warmup, each member with its own alpha and
    D_warmup (botorl.boto.phase.boto_updates in the stage loop, with this run's logs and
    checkpoints). The batches of a call follow from its index (boto_updates): no generator state
    to save, and calls are not cut at checkpoint points (train_boto's calls, so its numbers); the
    metrics are checked after every call, and a log point logs its call's."""

    name = "boto"
    check_every_call = True

    def __init__(self, run):
        cfg, bc = run.cfg, run.cfg.boto
        super().__init__(run, Schedule(bc.boto_steps, max(cfg.offline.log_every, bc.steps_per_call), cfg.checkpoint_every))
        self.alphas = [c.alpha for c in self.member_cfgs]

    def chunk(self, step: int) -> int:
        return min(self.cfg.boto.steps_per_call, self.cfg.boto.boto_steps - step)

    def log(self, step: int, ms: list[dict]) -> None:
        self.run.log(self.name, step, [{"seconds": time.perf_counter() - self.t0, **m} for m in ms])
        self.bar.set_postfix(loss=f"{ms[0]['critic_loss']:.3g}", q_data=f"{ms[0]['q_data']:.3g}")

    def train(self, agents, resume: dict | None = None):
        start = 0
        if resume is not None:
            agents, start = resume["agents"](agents), int(resume["step"])
        self.update = boto_updates(agents, self.run.d_offline, self.run.d_warmups or [None] * self.n, self.cfg.boto,
                                   self.alphas, [Streams.of(c).boto for c in self.member_cfgs])
        self.t0 = time.perf_counter()
        label = f"BOTO alpha={self.alphas[0]:+.2f}" if self.n == 1 else f"BOTO x {self.n} members"
        agents = stage_loop(self, agents, start, label)
        self.run.log_q(self.name, self.cfg.boto.boto_steps, agents)
        return agents


# ---------------------------------------------------------------------------- stage 3
class Finetune(Stage):
    """Online learning: the online loop ``state`` (``run.online_loop``: after the warm-up, where it
    left it; resumed, as the runner restores it) from its step to ``online.steps`` (the warm-up's
    env steps counted, as WSRL) with the fine-tuning learners, evaluating at its start, at
    ``eval.due`` points and at the end; what decides the future besides the agents is ``state``.
    Every method with a warm-up starts warm (configs/methods.py), so its buffer keeps D_warmup."""

    name = "finetune"

    def __init__(self, run):
        cfg, oc = run.cfg, run.cfg.online
        due = lambda step: cfg.eval.due(step, oc.steps, cfg.warmup.steps)  # noqa: E731
        super().__init__(run, Schedule(oc.steps, oc.log_every, cfg.checkpoint_every, due))

    def log(self, step: int, ms: list[dict]) -> None:
        self.run.log(self.name, step, self.state.log_rows(ms, self.rate(step)))

    def evaluate(self, agents, step: int) -> None:
        self.bar.set_postfix(success=f"{self.run.evaluate(agents, step)[0]['success']:.2f}")

    def save(self, step: int, agents, interrupted: bool) -> None:
        sd, w = self.state.state_dict(), self.window.state_dict() if interrupted else None
        if w:
            sd["arrays"]["window"] = w
        self.run.save(self.name, step, agents, sd)

    def train(self, agents, resume: dict | None = None):
        cfg, run = self.cfg, self.run
        self.state = state = run.online_loop(resume)
        agents = start_finetuning(cfg, self.member_cfgs, run.method, agents, state.buffer.action_dim,
                                  run.probe.observations)
        if resume is not None:
            agents = resume["agents"](agents)
            self.window.load(resume["arrays"].get("window"))
        # where the updates keep them (members split over the CPU devices) from the first step on: on one
        # device, a resumed run's loaded agents would compile another policy program (other last bits)
        agents = population.placed(agents, every_leaf=True)[0]
        if resume is None:  # a checkpoint comes after a step: a resumed fine-tuning is past its start
            self.run.evaluate(agents, state.step)
        self.rate = Rate(state.step)
        label = f"fine-tune ({cfg.method})" + (f" x {self.n} members" if self.n > 1 else "")
        with state:
            return stage_loop(self, agents, state.step, label, unit="env step")

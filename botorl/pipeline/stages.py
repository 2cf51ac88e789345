"""The four stages of a run. Each is a function from its config and inputs to its outputs.

    pretrain(ctx)                       -> agents     Cal-QL / CQL / IQL on D_offline
    warmup(ctx, agents)                 -> D_warmups  frozen policy, stochastic actions, no updates
    boto(ctx, agents, d_warmups)        -> agents     BOTO critic training on D_offline u D_warmup
    finetune(ctx, agents, d_warmups)    -> agents     online learning (WSRL / continued / scratch)

Every stage runs a population (botorl.pipeline.population): ``agents`` is the members' agent
pytrees stacked on a leading axis, ``d_warmups`` one D_warmup per member, and every update,
policy call and evaluation is ONE jitted call for all members. A single run is a population
of one, on this same path (its calls are then the agent's own jitted functions). Members run
in lockstep on the same step counts; each draws its batches, actions, env seeds and noise
from streams seeded by its own seed only (``ctx.members[i].cfg``), so a member's numbers do
not depend on the others.

``ctx`` (RunContext, runner.py) holds the config, task, run directory, loggers, the
transformed offline data and the checkpoint helpers. Each stage checkpoints at its end (the
runner does that) and pre-training, BOTO and fine-tuning every ``checkpoint_every`` steps
inside; given ``resume`` (the state of a mid-stage checkpoint) a stage continues from it
exactly: a mid-stage checkpoint holds everything that decides the stage's future (agents
with their JAX keys, every NumPy generator, the replay buffer, each env's full state
mid-episode, the episode counters, the metric windows, the evaluation schedule), and log
and checkpoint points are functions of the step alone. The warm-up has no mid-stage
checkpoint: it is short, and a resume after a kill inside it runs it again from its start,
which gives the same D_warmup (its envs, seeds and the policy's key come from the
pre-training checkpoint and the member's seed). tests/test_reliability_resume.py checks
that a resumed run's eval.csv, summary and metrics equal an uninterrupted run's.

Divergence: every stage checks each member's losses for NaN/inf before each checkpoint and
at each log point. A population of one raises TrainingDivergedError there without writing a
checkpoint, so the last good one stays; in a larger population that member is marked failed
(its summary says why) and the others go on, unless none is left.
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from botorl.data.dataset import Dataset
from botorl.pipeline import faults
from botorl.pipeline import population as P
from botorl.errors import ConfigError, TrainingDivergedError
from botorl.pipeline.methods import get_method

STAGES = ("pretrain", "warmup", "boto", "finetune")


# ---------------------------------------------------------------------------- helpers
@jax.jit
def _q_mean(agent, observations, actions):
    """Mean over the critic ensemble of Q(s, a): (B,)."""
    return agent.critic_values(agent.critic.params, observations, actions).mean(axis=0)


def q_fn(agent):
    return lambda o, a: np.asarray(_q_mean(agent, jnp.asarray(o), jnp.asarray(a)))


def make_pretrain_agent(cfg, obs_dim: int, action_dim: int, seed: int):
    if cfg.pretrain == "iql":
        from botorl.agents.iql import IQLAgent

        return IQLAgent.create(cfg.offline.iql, obs_dim, action_dim, seed)
    from botorl.agents.cql import CQLAgent

    return CQLAgent.create(cfg.offline.cql, obs_dim, action_dim, seed)


def make_online_agent_template(cfg, obs_dim: int, action_dim: int, seed: int):
    """An agent with the structure of the fine-tuning learner (for checkpoint loading)."""
    if get_method(cfg.method).online == "continue":
        return make_pretrain_agent(cfg, obs_dim, action_dim, seed)
    from botorl.agents.sac import SACAgent

    return SACAgent.create(cfg.online.sac, obs_dim, action_dim, seed)


def _finite_or_raise(stage: str, step: int, metrics: dict[str, float], ctx) -> None:
    bad = {k: v for k, v in metrics.items() if isinstance(v, float) and not math.isfinite(v)}
    if bad:
        last = ctx.ckpt.latest()
        where = f"checkpoint {last['name']}" if last else "no checkpoint yet"
        raise TrainingDivergedError(
            f"training diverged in stage {stage!r} near step {step}: "
            + ", ".join(f"{k} = {v}" for k, v in sorted(bad.items()))
            + f". The last good state is kept ({where} in {ctx.run.checkpoints}). Lower the learning rates "
            f"(e.g. --offline.cql.critic_lr, --online.sac.critic_lr), check the data's reward scale, or run "
            f"another seed; `botorl resume` would start again from that checkpoint."
        )


def _to_floats(metrics: dict) -> dict[str, float]:
    out = {}
    for k, v in jax.device_get(metrics).items():
        arr = np.asarray(v)
        if arr.size == 1:
            out[k] = float(arr.reshape(()))
    return out


def _mean_metrics(rows: list[dict]) -> dict[str, float]:
    if not rows:
        return {}
    rows = jax.device_get(rows)
    keys = rows[0].keys()
    return {k: float(np.mean([np.asarray(r[k]).mean() for r in rows])) for k in keys if np.asarray(rows[0][k]).size == 1}


def _check_members(stage: str, step: int, ms: list[dict[str, float]], ctx) -> None:
    """Each live member's metrics must be finite: a population of one raises (the last good
    checkpoint stays); in a larger one a diverged member is marked failed and the rest go on."""
    if ctx.n == 1:
        _finite_or_raise(stage, step, ms[0] if ms else {}, ctx)
        return
    for i, m in enumerate(ms):
        bad = {k: v for k, v in m.items() if not math.isfinite(v)}
        if bad and i not in ctx.failed:
            ctx.fail_member(i, f"training diverged in stage {stage!r} near step {step}: "
                            + ", ".join(f"{k} = {v}" for k, v in sorted(bad.items()))
                            + ". The other members went on. Lower the learning rates or run another seed.")
    if len(ctx.failed) == ctx.n:
        raise TrainingDivergedError(f"every member of the population diverged (stage {stage!r}, near step {step}); "
                                    f"each member's summary.json says how. Lower the learning rates "
                                    f"(e.g. --online.sac.critic_lr) or check the data's reward scale.")


def _per_member(metrics) -> list[dict]:
    """Stacked metrics {name: (N,)} -> one dict of floats per member (one host transfer)."""
    host = jax.device_get(metrics)
    n = len(next(iter(host.values())))
    return [{k: float(np.asarray(v)[i]) for k, v in host.items() if np.asarray(v)[i].size == 1} for i in range(n)]


def _bar(ctx, total: int, initial: int, desc: str, unit: str = "step"):
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, desc=desc, unit=unit, dynamic_ncols=True,
                disable=not ctx.cfg.progress, mininterval=1.0, smoothing=0.05)


def _rng_state(rng: np.random.Generator) -> dict:
    return rng.bit_generator.state


def _rng_from(state: dict | None, seed_seq) -> np.random.Generator:
    rng = np.random.default_rng(seed_seq)
    if state is not None:
        rng.bit_generator.state = state
    return rng


def _fill_mc_returns(ctx, buffer, rows: list[int], member: int | None = None) -> None:
    """Monte-Carlo returns of one finished online episode, by the offline data's rule
    (``member``: that member's rows of a ``MemberReplay``)."""
    if not rows:
        return
    idx = np.asarray(rows) if member is None else (member, np.asarray(rows))
    ep = Dataset(buffer.observations[idx], buffer.actions[idx], buffer.rewards[idx], buffer.next_observations[idx],
                 buffer.dones[idx] > 0.5, metadata={"source": "online episode"})
    buffer.mc_returns[idx] = ctx.mc_returns(ep)


def _rngs(ctx, stream: int, states=None, online: bool = False) -> list[np.random.Generator]:
    """Each member's generator of one stream, from its own seed (``online``: its online seed;
    restored from ``states``)."""
    states = states if isinstance(states, list) else [states] * ctx.n
    return [_rng_from(st, [mc.cfg.online_seed if online else mc.cfg.seed, stream])
            for mc, st in zip(ctx.members, states)]


def _reseed_online(ctx, agents):
    """The pre-trained agents' keys, folded with ``online_reseed`` for the members that set it,
    so their warm-up (and BOTO) draws differ from the runs they share the pre-training with."""
    reseeds = [mc.cfg.online_reseed for mc in ctx.members]
    if not any(reseeds):
        return agents
    keys = [jax.random.fold_in(P.member_of(agents, i).rng, k) if k else P.member_of(agents, i).rng
            for i, k in enumerate(reseeds)]
    return agents.replace(rng=jnp.stack(keys))


def _rng_states(rngs) -> list[dict]:
    return [_rng_state(r) for r in rngs]


# ---------------------------------------------------------------------------- stage 1
def pretrain(ctx, resume: dict | None = None):
    """Offline pre-training with the configured algorithm on the transformed D_offline (held
    once; each member samples its own batches)."""
    cfg = ctx.cfg
    d = ctx.d_offline
    # Members of one seed differ only in BOTO's alpha, which pre-training does not read: they
    # share one pre-training (computed once, by the first of them; mid-stage checkpoints hold
    # one agent per seed) and each gets its copy at the end.
    reps, group = pretrain_groups(ctx.members)
    seeds = [ctx.members[r].cfg.seed for r in reps]
    agents = P.stack([make_pretrain_agent(ctx.members[r].cfg, d.obs_dim, d.action_dim, ctx.members[r].cfg.seed)
                      for r in reps])
    step = 0
    rngs = [_rng_from(None, [s, 1]) for s in seeds]
    if resume is not None:
        agents = ctx.load_agents(resume["name"], agents)
        step = int(resume["step"])
        states = resume.get("np_rng")
        states = states if isinstance(states, list) else [states] * len(reps)
        if len(states) != len(reps):
            raise ConfigError(
                f"checkpoint {resume['name']!r} holds {len(states)} pre-training generators for {len(reps)} seeds: it was "
                f"written by a botorl that pre-trained every member separately. Resume from a checkpoint of another "
                f"stage (botorl resume DIR --from NAME) or start the population again."
            )
        rngs = [_rng_from(st, [s, 1]) for s, st in zip(seeds, states)]
    total = cfg.offline.steps
    K = cfg.offline.updates_per_call
    B = cfg.offline.batch_size
    every = cfg.checkpoint_every
    log_every = cfg.offline.log_every
    window: list[dict] = []
    on_device = cfg.offline.sample_on_device
    if on_device is None:
        on_device = jax.default_backend() != "cpu"
    if on_device:
        arrays = d.to_device()
        # the key of each call follows from (seed, step), so a resumed run draws the same batches
        base_keys = [jax.random.PRNGKey(s * 1_000_003 + 1) for s in seeds]
    shared = f" x {len(reps)} seeds for {ctx.n} members" if len(reps) < ctx.n else f" x {ctx.n} members"
    bar = _bar(ctx, total, step, f"pretrain ({cfg.pretrain})" + (shared if ctx.n > 1 else ""))
    t_last, n_last = time.perf_counter(), step
    try:
        while step < total:
            # chunk ends at the next checkpoint boundary so that checkpoints land on multiples
            k = min(K, total - step, every - step % every)
            if on_device:
                keys = jnp.stack([jax.random.fold_in(bk, step) for bk in base_keys])
                agents, metrics = P.pop_update_many_on_device(agents, arrays, keys, k, B)
            else:
                agents, metrics = P.pop_update_many(agents, P.sample_members(d, rngs, B, k))
            window.append(metrics)
            prev, step = step, step + k
            bar.update(k)
            crossed_log = step // log_every > prev // log_every or step == total
            crossed_ckpt = step % every == 0 and step < total
            if crossed_log or crossed_ckpt:
                per_seed = _window_means(window)
                ms = [per_seed[g] for g in group]
                window = []
                _check_members("pretrain", step, ms, ctx)
                if crossed_log:
                    now = time.perf_counter()
                    for mc, m in ctx.live(ms):
                        m["steps_per_s"] = (step - n_last) / max(now - t_last, 1e-9)
                        mc.logger.log("pretrain", step, m)
                    t_last, n_last = now, step
                    m = ms[0]
                    bar.set_postfix(loss=f"{m.get('critic_loss', float('nan')):.3g}", q=f"{m.get('q_data', float('nan')):.3g}")
            if crossed_ckpt:
                ctx.save_mid("pretrain", step, agents, np_rng=_rng_states(rngs))
            faults.step("pretrain", step)
    finally:
        bar.close()
    if len(reps) < ctx.n:
        agents = jax.tree_util.tree_map(lambda x: x[np.asarray(group)], agents)
    return agents


def pretrain_groups(members) -> tuple[list[int], list[int]]:
    """(the first member of each seed, each member's index into that list)."""
    first: dict[int, int] = {}
    group = [first.setdefault(mc.cfg.seed, len(first)) for mc in members]
    return [group.index(g) for g in range(len(first))], group


def _window_means(window: list[dict]) -> list[dict[str, float]]:
    """Per member, the mean over the window of each scalar metric (one host transfer)."""
    if not window:
        return []
    host = jax.device_get(window)
    n = len(next(iter(host[0].values())))
    keys = [k for k, v in host[0].items() if np.asarray(v).shape == (n,)]
    return [{k: float(np.mean([np.asarray(w[k])[i] for w in host])) for k in keys} for i in range(n)]


# ---------------------------------------------------------------------------- stage 2a
def warmup(ctx, agents) -> tuple[list[Dataset] | None, Any]:
    """D_warmup: ``warmup.steps`` env steps of the frozen pre-trained policy (stochastic), one
    env per member, stepped together with one policy call per step for all members.

    These are the first online env steps (WSRL's accounting): the online axis starts here,
    with an evaluation of the pre-trained policy at step 0 and at every evaluation point the
    warm-up passes (the policy is frozen and its evaluation deterministic, so the step-0
    evaluation is logged again there instead of being run again).

    No mid-stage checkpoint: a run killed here starts the warm-up again from its beginning on
    resume, which is exact (the same env seeds, and the policy's key from the pre-training
    checkpoint), and costs at most ``warmup.steps`` env steps of a frozen policy."""
    cfg = ctx.cfg
    spec = ctx.spec
    n = cfg.warmup.steps
    if n == 0:
        return None, agents
    N = ctx.n
    envs = [spec.make_env(seed=mc.cfg.online_seed * 1000 + 7) for mc in ctx.members]
    obs = np.stack([np.asarray(e.reset(seed=mc.cfg.online_seed * 1000 + 7)[0], np.float32)
                    for e, mc in zip(envs, ctx.members)])
    agents = _reseed_online(ctx, agents)
    O, A = ctx.d_offline.obs_dim, ctx.d_offline.action_dim
    rows = {
        "observations": np.zeros((N, n, O), np.float32),
        "actions": np.zeros((N, n, A), np.float32),
        "rewards": np.zeros((N, n), np.float32),
        "next_observations": np.zeros((N, n, O), np.float32),
        "terminals": np.zeros((N, n), bool),
        "episode_ends": np.zeros((N, n), bool),
    }
    successes: list[list[float]] = [[] for _ in range(N)]
    ep_success = np.zeros(N)
    bar = _bar(ctx, n, 0, "warm-up (frozen policy)", unit="env step")
    first_eval = None
    try:
        for t in range(n):
            if t % cfg.eval.interval == 0:
                first_eval = ctx.evaluate(agents, t) if first_eval is None else ctx.log_evaluation(first_eval, t)
            actions, agents = P.pop_sample(agents, obs)
            actions = np.asarray(actions, dtype=np.float32)
            for i, env in enumerate(envs):
                next_obs, r, terminated, truncated, info = env.step(actions[i])
                ep_success[i] = max(ep_success[i], float(info.get("success", 0.0)))
                rows["observations"][i, t] = obs[i]
                rows["actions"][i, t] = actions[i]
                rows["rewards"][i, t] = r
                rows["next_observations"][i, t] = next_obs
                rows["terminals"][i, t] = terminated
                rows["episode_ends"][i, t] = terminated or truncated
                obs[i] = next_obs
                if terminated or truncated:
                    successes[i].append(ep_success[i])
                    ep_success[i] = 0.0
                    obs[i] = env.reset()[0]
            if t % 200 == 0:
                bar.update(min(200, n - bar.n))
            faults.step("warmup", t + 1)
        bar.update(n - bar.n)
    finally:
        bar.close()
        for env in envs:
            env.close()
    d_warmups = []
    for i, mc in enumerate(ctx.members):
        d_raw = Dataset(**{k: v[i] for k, v in rows.items()},
                        metadata={"source": f"D_warmup ({n} steps of the pre-trained policy)"})
        d_warmups.append(ctx.transform(d_raw))
        if i not in ctx.failed:
            mc.logger.log("warmup", n, {
                "episodes": len(successes[i]),
                "success_rate": float(np.mean(successes[i])) if successes[i] else float("nan"),
                "reward_mean": float(np.mean(rows["rewards"][i])) if n else float("nan"),
            })
    return d_warmups, agents


# ---------------------------------------------------------------------------- stage 2b
def boto(ctx, agents, d_warmups: list[Dataset] | None, resume: dict | None = None):
    """BOTO critic training on D_offline u D_warmup, each member with its own alpha and its own
    D_warmup (the loop of botorl.boto.phase.run_boto, all members per jitted call)."""
    from botorl.boto.objective import ObjectiveSettings

    cfg = ctx.cfg
    bc = cfg.boto
    start = 0
    if resume is not None:
        agents = ctx.load_agents(resume["name"], agents)
        start = int(resume["step"])
    every = cfg.checkpoint_every
    log_every = max(cfg.offline.log_every, bc.steps_per_call)
    settings = ObjectiveSettings.resolve(bc, P.member_of(agents, 0))
    alphas = np.asarray([mc.cfg.boto.alpha for mc in ctx.members], np.float32)
    warm = d_warmups if d_warmups is not None else [None] * ctx.n
    end = bc.boto_steps
    t0 = time.perf_counter()
    step = start
    label = f"BOTO alpha={alphas[0]:+.2f}" if ctx.n == 1 else f"BOTO x {ctx.n} members"
    bar = _bar(ctx, end, start, label)
    try:
        while step < end:
            k = min(bc.steps_per_call, end - step)
            call_index = step // bc.steps_per_call
            # the batches of call c come from default_rng([seed, c]) (run_boto's rule): a
            # resumed phase draws the same data stream
            rngs = [np.random.default_rng([mc.cfg.boto.seed, call_index]) for mc in ctx.members]
            batches = P.sample_union_members(ctx.d_offline, warm, rngs, bc.batch_size, k)
            new_agents, metrics = P.pop_boto_update_many(agents, batches, alphas, settings)
            ms = _per_member(metrics)
            _check_members("boto", step + k, ms, ctx)
            agents = new_agents
            prev, step = step, step + k
            bar.update(k)
            m0 = ms[0]
            bar.set_postfix(loss=f"{m0['critic_loss']:.3g}", q_data=f"{m0['q_data']:.3g}", q_unif=f"{m0['q_uniform']:.3g}")
            # log and checkpoint points follow from the step alone, so a resumed phase keeps them
            if step // log_every > prev // log_every or step == end:
                secs = time.perf_counter() - t0
                for mc, m in ctx.live(ms):
                    mc.logger.log("boto", step, {"seconds": secs, **m})
            if step // every > prev // every and step < end:
                ctx.save_mid("boto", step, agents)
            faults.step("boto", step)
    finally:
        bar.close()
    return agents


# ---------------------------------------------------------------------------- stage 3
def finetune(ctx, agents, d_warmups: list[Dataset] | None, resume: dict | None = None):
    """Online learning, from the online step after the warm-up (0 for methods without one) to
    ``online.steps``; evaluates when it starts, every ``eval.interval`` steps and at the end.

    One online axis for every method: the warm-up's env steps are online steps (WSRL), so a
    method with a 5,000-step warm-up fine-tunes for ``online.steps - 5,000`` env steps.

    Members step their own envs in lockstep: one policy call for all per env step, one
    replay buffer with a member axis (each member's rows its own), one batched UTD update."""
    from botorl.agents.sac import SACAgent

    cfg = ctx.cfg
    spec = ctx.spec
    oc = cfg.online
    N = ctx.n
    flavour = get_method(cfg.method).online
    O, A = ctx.d_offline.obs_dim, ctx.d_offline.action_dim
    n_warm = len(d_warmups[0]) if d_warmups is not None else 0
    capacity = oc.buffer_capacity or (oc.steps + n_warm + 1)

    if flavour == "wsrl":
        # WSRL's warm start: SAC (10 critics) from the pre-trained (or BOTO-trained) networks.
        # From IQL (no temperature) the initial one comes from the probe states (agents/temperature.py).
        agents = P.stack([SACAgent.from_pretrained(P.member_of(agents, i), oc.sac, seed=mc.cfg.online_seed * 7919 + 3,
                                                   observations=ctx.probe.observations)
                          for i, mc in enumerate(ctx.members)])
    elif flavour == "scratch":
        agents = P.stack([SACAgent.create(oc.sac, O, A, mc.cfg.online_seed) for mc in ctx.members])
    # "continue": the pre-trained agent keeps its own loss
    buffer = P.MemberReplay(N, capacity, O, A)
    start = n_warm  # the warm-up's env steps came first
    step = start
    rngs = _rngs(ctx, 3, online=True)
    extra: dict = {}
    if resume is not None:
        agents = ctx.load_agents(resume["name"], agents)
        step = int(resume["step"])
        rngs = _rngs(ctx, 3, resume.get("np_rng"), online=True)
        buffer = P.MemberReplay.from_state_dict(ctx.ckpt.arrays(resume["name"], "buffer"))
        extra = resume.get("extra", {})
        start = int(extra.get("start", start))
    elif d_warmups is not None and flavour == "wsrl":
        buffer.insert_datasets(d_warmups)  # WSRL: the online buffer starts with D_warmup

    first = P.member_of(agents, 0)
    is_iql = type(first).__name__ == "IQLAgent"
    u, B = oc.utd, oc.batch_size
    offline = ctx.d_offline if oc.offline_ratio > 0 else None
    # Cal-QL continued online bounds Q by each row's MC return, known once its episode ends
    # (filled in then): it samples finished episodes only and waits for the first one (WSRL).
    needs_mc = bool(getattr(first.config, "calql", False))

    def batch(active):
        b = buffer.sample_active(rngs, active, B, u, finished=needs_mc, offline=offline,
                                 offline_ratio=oc.offline_ratio)
        if is_iql:
            return b  # (N, u, B, ...) -> update_many
        # (N, u, B, ...) -> (N, u*B, ...): each critic minibatch keeps the offline/online mix
        return {k: v.reshape((N, u * B) + v.shape[3:]) for k, v in b.items()}

    resumes = int(extra.get("resumes", 0)) + (1 if resume is not None else 0)
    env_seeds = [mc.cfg.online_seed * 1000 + 11 for mc in ctx.members]
    envs = [spec.make_env(seed=s) for s in env_seeds]
    ep_succ = np.zeros(N)
    ep_rows: list[list[int]] = [[] for _ in range(N)]
    recent_success: list[list[float]] = [[] for _ in range(N)]
    online = _load_online_state(ctx, resume, envs) if resume is not None else None
    if online is not None:  # continue every member's episode where the checkpoint left it
        obs, ep_succ, ep_rows, recent_success = online
    else:
        if resume is not None:
            # a checkpoint written before env states were saved: each member starts a new episode,
            # with seeds not used before (the run is then not exact)
            print("botorl: warning: this checkpoint has no env state (written by an older botorl); fine-tuning "
                  "continues with new episodes, so the run will not repeat an uninterrupted one exactly.",
                  file=sys.stderr)
            env_seeds = [s + 100_003 * resumes for s in env_seeds]
        obs = np.stack([np.asarray(e.reset(seed=s)[0], np.float32) for e, s in zip(envs, env_seeds)])
    tf = spec.reward_transform
    episodes = extra.get("episodes", 0)
    episodes = list(episodes) if isinstance(episodes, list) else [int(episodes)] * N
    window: list[tuple[dict, np.ndarray]] = []  # (metrics (N,), which members updated)
    total = oc.steps
    last_eval = int(extra.get("last_eval", -1))

    if step == start and last_eval < start:
        ctx.evaluate(agents, start)
        last_eval = start
    bar = _bar(ctx, total, step, f"fine-tune ({cfg.method})" + (f" x {N} members" if N > 1 else ""), unit="env step")
    t_last, n_last = time.perf_counter(), step
    rewards = np.zeros(N, np.float32)
    dones = np.zeros(N, np.float32)
    next_obs = np.zeros_like(obs)
    try:
        while step < total:
            actions, agents = P.pop_sample(agents, obs)
            actions = np.asarray(actions, dtype=np.float32)
            ended = []
            for i, env in enumerate(envs):
                o2, r, terminated, truncated, info = env.step(actions[i])
                next_obs[i] = o2
                rewards[i] = tf(float(r))
                dones[i] = float(terminated)
                s = float(info.get("success", 0.0))
                ep_succ[i] = max(ep_succ[i], s) if spec.success_mode == "any" else s
                if terminated or truncated:
                    ended.append(i)
            for i in range(N):
                ep_rows[i].append(buffer.insert_index)
            buffer.insert(obs, actions, rewards, next_obs, dones)
            obs[:] = next_obs
            for i in ended:
                if needs_mc:
                    _fill_mc_returns(ctx, buffer, ep_rows[i], member=i)
                buffer.end_episode(i)
                ep_rows[i] = []
                episodes[i] += 1
                recent_success[i].append(ep_succ[i])
                obs[i] = envs[i].reset()[0]
                ep_succ[i] = 0.0
            if step >= oc.random_steps:
                online_len = [buffer.finished_len(i) if needs_mc else len(buffer) for i in range(N)]
                active = [n_i > 0 or (offline is not None and not needs_mc) for n_i in online_len]
                if all(active):
                    agents, metrics = (P.pop_update_many if is_iql else P.pop_update)(agents, batch(active))
                elif any(active):
                    agents, metrics = P.pop_update_masked(agents, batch(active), np.asarray(active), many=is_iql)
                if any(active):
                    window.append((metrics, np.asarray(active)))
            step += 1
            bar.update(1)
            at_ckpt = step % cfg.checkpoint_every == 0 and step < total
            if step % oc.log_every == 0 or at_ckpt or step == total:
                ms = _masked_means(window, N)
                window = []
                _check_members("finetune", step, ms, ctx)
                if step % oc.log_every == 0 or step == total:
                    now = time.perf_counter()
                    for mc, m in ctx.live(ms):
                        i = ctx.members.index(mc)
                        m.update(episodes=episodes[i], env_steps_per_s=(step - n_last) / max(now - t_last, 1e-9),
                                 train_success=float(np.mean(recent_success[i])) if recent_success[i] else float("nan"),
                                 buffer_size=len(buffer))
                        mc.logger.log("finetune", step, m)
                    t_last, n_last = now, step
                    recent_success = [[] for _ in range(N)]
            if cfg.eval.due(step, total, cfg.warmup.steps):
                rows = ctx.evaluate(agents, step)
                last_eval = step
                bar.set_postfix(success=f"{rows[0]['success']:.2f}")
            if at_ckpt:
                ctx.save_mid("finetune", step, agents, np_rng=_rng_states(rngs),
                             arrays={"buffer": buffer.state_dict(), "online": {"obs": obs, "ep_succ": ep_succ}},
                             extra={"episodes": episodes, "last_eval": last_eval,
                                    "resumes": resumes, "start": start},
                             documents={"envs": _online_document(envs, ep_rows, recent_success)})
            faults.step("finetune", step)
    finally:
        bar.close()
        for env in envs:
            env.close()
    return agents


def _online_document(envs, ep_rows, recent_success) -> dict:
    """What of fine-tuning's running episodes is not in arrays: each member's env state
    (botorl.envs.state), the buffer rows of its running episode (their Monte-Carlo returns
    are filled when it ends) and the episode successes since the last log point."""
    from botorl.envs.state import get_env_state

    return {"envs": [get_env_state(e) for e in envs],
            "ep_rows": [[int(r) for r in rows] for rows in ep_rows],
            "recent_success": [[float(x) for x in xs] for xs in recent_success]}


def _load_online_state(ctx, resume: dict, envs):
    """(obs, ep_succ, ep_rows, recent_success) from a fine-tuning checkpoint, with each env set
    to its saved state; None for a checkpoint without env states (older botorl)."""
    from botorl.envs.state import set_env_state
    from botorl.pipeline.checkpoint import CheckpointCorrupt

    doc = ctx.ckpt.document(resume["name"], "envs")
    arrays = ctx.ckpt.arrays(resume["name"], "online")
    if doc is None or arrays is None:
        return None
    try:
        if len(doc["envs"]) != len(envs) or arrays["obs"].shape[0] != len(envs):
            raise ValueError(f"it holds {len(doc['envs'])} envs, the run has {len(envs)} members")
        for env, st in zip(envs, doc["envs"]):
            set_env_state(env, st)
        obs = np.array(arrays["obs"], np.float32)
        ep_succ = np.array(arrays["ep_succ"], np.float64)
        ep_rows = [[int(r) for r in rows] for rows in doc["ep_rows"]]
        recent = [[float(x) for x in xs] for xs in doc["recent_success"]]
    except (KeyError, TypeError, ValueError, IndexError) as err:
        raise CheckpointCorrupt(
            f"checkpoint {resume['name']}: its env state (envs.json, online.npz) does not fit this run "
            f"({type(err).__name__}: {err}). Resume from another checkpoint: `botorl resume RUN_DIR --from NAME`."
        ) from None
    return obs, ep_succ, ep_rows, recent


def _masked_means(window: list[tuple[dict, np.ndarray]], n: int) -> list[dict[str, float]]:
    """Per member, the mean of each scalar metric over the updates it took part in."""
    if not window:
        return [{} for _ in range(n)]
    host = jax.device_get([w for w, _ in window])
    masks = np.stack([m for _, m in window])  # (T, N)
    keys = [k for k, v in host[0].items() if np.asarray(v).ndim == 1]
    out = []
    for i in range(n):
        rows = np.flatnonzero(masks[:, i])
        out.append({k: float(np.mean([np.asarray(host[t][k])[i] for t in rows])) for k in keys} if len(rows) else {})
    return out

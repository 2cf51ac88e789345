"""The four stages of a run. Each is a function from its config and inputs to its outputs.

    pretrain(ctx)                       -> agent      Cal-QL / CQL / IQL on D_offline
    warmup(ctx, agent)                  -> D_warmup   frozen policy, stochastic actions, no updates
    boto(ctx, agent, d_warmup)          -> agent      BOTO critic training on D_offline u D_warmup
    finetune(ctx, agent, d_warmup)      -> agent      online learning (WSRL / continued / scratch)

``ctx`` (RunContext, runner.py) holds the config, task, run directory, loggers, the
transformed offline data and the checkpoint helpers. Each stage checkpoints at its end (the
runner does that) and the long ones every ``checkpoint_every`` steps inside; given ``resume``
(the state of a mid-stage checkpoint) a stage continues from it.

Divergence: every stage checks its losses for NaN/inf before each checkpoint and at each log
point; on one it raises TrainingDivergedError without writing a checkpoint, so the last good
one stays.
"""

from __future__ import annotations

import math
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from botorl.agents.common import update_many_on_device
from botorl.data.dataset import Dataset
from botorl.errors import TrainingDivergedError
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


def _fill_mc_returns(ctx, buffer, rows: list[int]) -> None:
    """Monte-Carlo returns of one finished online episode, by the offline data's rule."""
    if not rows:
        return
    idx = np.asarray(rows)
    ep = Dataset(buffer.observations[idx], buffer.actions[idx], buffer.rewards[idx], buffer.next_observations[idx],
                 buffer.dones[idx] > 0.5, metadata={"source": "online episode"})
    buffer.mc_returns[idx] = ctx.mc_returns(ep)


# ---------------------------------------------------------------------------- stage 1
def pretrain(ctx, resume: dict | None = None):
    """Offline pre-training with the configured algorithm on the transformed D_offline."""
    cfg = ctx.cfg
    d = ctx.d_offline
    agent = make_pretrain_agent(cfg, d.obs_dim, d.action_dim, cfg.seed)
    step = 0
    rng = _rng_from(None, [cfg.seed, 1])
    if resume is not None:
        agent = ctx.load_agent(resume["name"], agent)
        step = int(resume["step"])
        rng = _rng_from(resume.get("np_rng"), [cfg.seed, 1])
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
        base_key = jax.random.PRNGKey(cfg.seed * 1_000_003 + 1)
    bar = _bar(ctx, total, step, f"pretrain ({cfg.pretrain})")
    t_last, n_last = time.perf_counter(), step
    try:
        while step < total:
            # chunk ends at the next checkpoint boundary so that checkpoints land on multiples
            k = min(K, total - step, every - step % every)
            if on_device:
                agent, metrics = update_many_on_device(agent, arrays, jax.random.fold_in(base_key, step), k, B)
            else:
                agent, metrics = agent.update_many(d.sample(rng, B, num_batches=k))
            window.append(metrics)
            prev, step = step, step + k
            bar.update(k)
            crossed_log = step // log_every > prev // log_every or step == total
            crossed_ckpt = step % every == 0 and step < total
            if crossed_log or crossed_ckpt:
                m = _mean_metrics(window)
                window = []
                _finite_or_raise("pretrain", step, m, ctx)
                if crossed_log:
                    now = time.perf_counter()
                    m["steps_per_s"] = (step - n_last) / max(now - t_last, 1e-9)
                    t_last, n_last = now, step
                    ctx.logger.log("pretrain", step, m)
                    bar.set_postfix(loss=f"{m.get('critic_loss', float('nan')):.3g}", q=f"{m.get('q_data', float('nan')):.3g}")
            if crossed_ckpt:
                ctx.save_mid("pretrain", step, agent, np_rng=_rng_state(rng))
    finally:
        bar.close()
    return agent


# ---------------------------------------------------------------------------- stage 2a
def warmup(ctx, agent) -> tuple[Dataset | None, Any]:
    """D_warmup: ``warmup.steps`` env steps of the frozen pre-trained policy (stochastic).

    These are the first online env steps (WSRL's accounting): the online axis starts here,
    with an evaluation of the pre-trained policy at step 0 and at every evaluation point the
    warm-up passes (the policy is frozen, so those show it unchanged)."""
    cfg = ctx.cfg
    spec = ctx.spec
    n = cfg.warmup.steps
    if n == 0:
        return None, agent
    env = spec.make_env(seed=cfg.seed * 1000 + 7)
    obs, _ = env.reset(seed=cfg.seed * 1000 + 7)
    O, A = ctx.d_offline.obs_dim, ctx.d_offline.action_dim
    rows = {
        "observations": np.zeros((n, O), np.float32),
        "actions": np.zeros((n, A), np.float32),
        "rewards": np.zeros((n,), np.float32),
        "next_observations": np.zeros((n, O), np.float32),
        "terminals": np.zeros((n,), bool),
        "episode_ends": np.zeros((n,), bool),
    }
    successes: list[float] = []
    ep_success = 0.0
    bar = _bar(ctx, n, 0, "warm-up (frozen policy)", unit="env step")
    try:
        for t in range(n):
            if t % cfg.eval.interval == 0:
                ctx.evaluate(agent, t)
            action, agent = agent.sample_actions(obs)
            action = np.asarray(action, dtype=np.float32)
            next_obs, r, terminated, truncated, info = env.step(action)
            ep_success = max(ep_success, float(info.get("success", 0.0)))
            rows["observations"][t] = obs
            rows["actions"][t] = action
            rows["rewards"][t] = r
            rows["next_observations"][t] = next_obs
            rows["terminals"][t] = terminated
            rows["episode_ends"][t] = terminated or truncated
            obs = next_obs
            if terminated or truncated:
                successes.append(ep_success)
                ep_success = 0.0
                obs, _ = env.reset()
            if t % 200 == 0:
                bar.update(min(200, n - bar.n))
        bar.update(n - bar.n)
    finally:
        bar.close()
        env.close()
    d_raw = Dataset(**rows, metadata={"source": f"D_warmup ({n} steps of the pre-trained policy)"})
    d_warmup = ctx.transform(d_raw)
    ctx.logger.log("warmup", n, {
        "episodes": len(successes),
        "success_rate": float(np.mean(successes)) if successes else float("nan"),
        "reward_mean": float(np.mean(rows["rewards"])) if n else float("nan"),
    })
    return d_warmup, agent


# ---------------------------------------------------------------------------- stage 2b
def boto(ctx, agent, d_warmup: Dataset | None, resume: dict | None = None):
    """BOTO critic training on D_offline u D_warmup (botorl.boto.phase.run_boto)."""
    from botorl.boto.phase import run_boto

    cfg = ctx.cfg
    start = 0
    if resume is not None:
        agent = ctx.load_agent(resume["name"], agent)
        start = int(resume["step"])
    every = cfg.checkpoint_every
    log_every = max(cfg.offline.log_every, cfg.boto.steps_per_call)
    state = {"last_ckpt": start, "last_log": start}

    def callback(step: int, a, record: dict) -> None:
        m = {k: v for k, v in record.items() if k != "step"}
        _finite_or_raise("boto", step, m, ctx)
        if step - state["last_log"] >= log_every or step == cfg.boto.boto_steps:
            ctx.logger.log("boto", step, m)
            state["last_log"] = step
        if step - state["last_ckpt"] >= every and step < cfg.boto.boto_steps:
            ctx.save_mid("boto", step, a)
            state["last_ckpt"] = step

    agent, _ = run_boto(agent, ctx.d_offline, d_warmup, cfg.boto, start_step=start, callback=callback,
                        progress=cfg.progress)
    return agent


# ---------------------------------------------------------------------------- stage 3
def finetune(ctx, agent, d_warmup: Dataset | None, resume: dict | None = None):
    """Online learning, from the online step after the warm-up (0 for methods without one) to
    ``online.steps``; evaluates when it starts, every ``eval.interval`` steps and at the end.

    One online axis for every method: the warm-up's env steps are online steps (WSRL), so a
    method with a 5,000-step warm-up fine-tunes for ``online.steps - 5,000`` env steps."""
    from botorl.agents.sac import SACAgent
    from botorl.data.replay import ReplayBuffer, sample_mixed
    cfg = ctx.cfg
    spec = ctx.spec
    oc = cfg.online
    flavour = get_method(cfg.method).online
    O, A = ctx.d_offline.obs_dim, ctx.d_offline.action_dim
    capacity = oc.buffer_capacity or (oc.steps + (len(d_warmup) if d_warmup is not None else 0) + 1)

    if flavour == "wsrl":
        # WSRL's warm start: SAC (10 critics) from the pre-trained (or BOTO-trained) networks.
        agent = SACAgent.from_pretrained(agent, oc.sac, seed=cfg.seed * 7919 + 3)
    elif flavour == "scratch":
        agent = SACAgent.create(oc.sac, O, A, cfg.seed)
    # "continue": the pre-trained agent keeps its own loss
    buffer = ReplayBuffer(capacity, O, A)
    start = len(d_warmup) if d_warmup is not None else 0  # the warm-up's env steps came first
    step = start
    rng = _rng_from(None, [cfg.seed, 3])
    extra: dict = {}
    if resume is not None:
        agent = ctx.load_agent(resume["name"], agent)
        step = int(resume["step"])
        rng = _rng_from(resume.get("np_rng"), [cfg.seed, 3])
        buf_state = ctx.ckpt.arrays(resume["name"], "buffer")
        buffer = ReplayBuffer.from_state_dict(buf_state)
        extra = resume.get("extra", {})
        start = int(extra.get("start", start))
    elif d_warmup is not None and flavour == "wsrl":
        buffer.insert_dataset(d_warmup)  # WSRL: the online buffer starts with D_warmup

    is_iql = type(agent).__name__ == "IQLAgent"
    u, B = oc.utd, oc.batch_size
    offline = ctx.d_offline if oc.offline_ratio > 0 else None
    # Cal-QL continued online bounds Q by each row's MC return, known once its episode ends
    # (filled in then): it samples finished episodes only and waits for the first one (WSRL).
    needs_mc = bool(getattr(agent.config, "calql", False))
    online_rows = buffer.finished() if needs_mc else buffer

    def batch():
        if offline is not None:
            b = sample_mixed([offline, online_rows], [oc.offline_ratio, 1.0 - oc.offline_ratio], rng, B, num_batches=u)
        else:
            b = online_rows.sample(rng, B, num_batches=u)
        if is_iql:
            return b  # (u, B, ...) -> update_many
        # (u, B, ...) -> (u*B, ...): each critic minibatch keeps the offline/online mix
        return {k: v.reshape((u * B,) + v.shape[2:]) for k, v in b.items()}

    resumes = int(extra.get("resumes", 0)) + (1 if resume is not None else 0)
    # a resumed run starts a new episode (env state is not checkpointed) with fresh seeds
    env_seed = cfg.seed * 1000 + 11 + 100_003 * resumes
    env = spec.make_env(seed=env_seed)
    obs, _ = env.reset(seed=env_seed)
    tf = spec.reward_transform
    ep_ret, ep_succ, ep_len = 0.0, 0.0, 0
    ep_rows: list[int] = []
    episodes = int(extra.get("episodes", 0))
    recent_success: list[float] = []
    window: list[dict] = []
    total = oc.steps
    last_eval = int(extra.get("last_eval", -1))

    if step == start and last_eval < start:
        ctx.evaluate(agent, start)
        last_eval = start
    bar = _bar(ctx, total, step, f"fine-tune ({cfg.method})", unit="env step")
    t_last, n_last = time.perf_counter(), step
    try:
        while step < total:
            if step < oc.random_steps:
                action = rng.uniform(-1.0, 1.0, size=A).astype(np.float32)
            else:
                action, agent = agent.sample_actions(obs)
                action = np.asarray(action, dtype=np.float32)
            next_obs, r, terminated, truncated, info = env.step(action)
            ep_rows.append(buffer.insert_index)
            buffer.insert(obs, action, tf(float(r)), next_obs, terminated)
            ep_ret += float(r)
            ep_len += 1
            ep_succ = max(ep_succ, float(info.get("success", 0.0))) if spec.success_mode == "any" else float(info.get("success", 0.0))
            obs = next_obs
            if terminated or truncated:
                if needs_mc:
                    _fill_mc_returns(ctx, buffer, ep_rows)
                buffer.end_episode()
                ep_rows = []
                episodes += 1
                recent_success.append(ep_succ)
                obs, _ = env.reset()
                ep_ret, ep_succ, ep_len = 0.0, 0.0, 0
            if step >= oc.random_steps and (len(online_rows) > 0 or (offline is not None and not needs_mc)):
                b = batch()
                agent, metrics = agent.update_many(b) if is_iql else agent.update(b)
                window.append(metrics)
            step += 1
            bar.update(1)
            at_ckpt = step % cfg.checkpoint_every == 0 and step < total
            if step % oc.log_every == 0 or at_ckpt or step == total:
                m = _mean_metrics(window)
                window = []
                _finite_or_raise("finetune", step, m, ctx)
                if step % oc.log_every == 0 or step == total:
                    now = time.perf_counter()
                    m.update(episodes=episodes, env_steps_per_s=(step - n_last) / max(now - t_last, 1e-9),
                             train_success=float(np.mean(recent_success)) if recent_success else float("nan"),
                             buffer_size=len(buffer))
                    t_last, n_last = now, step
                    recent_success = []
                    ctx.logger.log("finetune", step, m)
            if step % cfg.eval.interval == 0 or step == total:
                row = ctx.evaluate(agent, step)
                last_eval = step
                bar.set_postfix(success=f"{row['success']:.2f}")
            if at_ckpt:
                ctx.save_mid("finetune", step, agent, np_rng=_rng_state(rng),
                             arrays={"buffer": buffer.state_dict()},
                             extra={"episodes": episodes, "last_eval": last_eval,
                                    "resumes": resumes, "start": start})
    finally:
        bar.close()
        env.close()
    return agent

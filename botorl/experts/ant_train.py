"""Train the goal-reaching ant (``botorl.envs.ant_goal``) with botorl's SAC; resumable.

    botorl train-ant --out runs/ant_goal [--total-env-steps N] [--time-limit-s S] ...

Worker processes step the ants (``AntGoalSim``, a numpy copy of the previous iteration's
actor) while the accelerator runs ``updates_per_iter`` SAC updates on a replay buffer kept on
the device, so simulation and gradient steps overlap (``num_workers`` 0: the ants in this
process). Layout, checkpoints, resume and SAC settings: docs/antmaze.md; the initial
temperature 0.1 is Minari's ``ent_coef "auto_0.1"``. The replay buffer is not saved: a resumed
run refills it with ``start_steps`` of the restored policy.

Files under ``out``: ``agent.ckpt``, ``state.json``, ``curve.csv`` (one row per evaluation,
``CURVE_FIELDS``), ``actor.npz`` (the numpy actor, ``NumpyActor``), ``curve.png``.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
import json
import multiprocessing as mp
import os
import time
from dataclasses import dataclass
from functools import partial
from typing import Annotated
from pathlib import Path

import numpy as np
from tqdm import tqdm

from botorl.envs.ant_goal import ACTION_DIM, HORIZON, OBS_DIM, AntGoalSim, NumpyActor, actor_arrays
from botorl.errors import Range, check_ranges
from botorl.io import append_text, atomic_save_figure, atomic_write_bytes, atomic_write_json, pyplot
from botorl.jaxsetup import setup_jax


@dataclass
class AntTrainConfig:
    """Settings of ``botorl train-ant``."""

    out: str = "runs/ant_goal"
    """folder for the checkpoint, the learning curve and the exported actor (resumes from it)"""
    total_env_steps: Annotated[int, Range(1, 10**12)] = 20_000_000
    """stop after this many environment steps (all ants together)"""
    time_limit_s: Annotated[float, Range(0, 10**7)] = 0.0
    """stop (and checkpoint) after this many seconds of this call; 0 = no limit"""
    seed: Annotated[int, Range(0, 2**31 - 1)] = 0
    num_workers: Annotated[int, Range(0, 1024)] = 0
    """simulation processes; 0 = step the ants in this process"""
    envs_per_worker: Annotated[int, Range(1, 1024)] = 4
    rollout_len: Annotated[int, Range(1, 10**6)] = 8
    """env steps per ant per iteration"""
    updates_per_iter: Annotated[int, Range(1, 10**4)] = 16
    batch_size: Annotated[int, Range(1, 1 << 20)] = 1024
    buffer_size: Annotated[int, Range(1, 10**9)] = 2_000_000
    start_steps: Annotated[int, Range(0, 10**12)] = 50_000
    """random-action steps before the first update (and after a resume: policy steps)"""
    hidden: tuple[int, ...] = (256, 256, 256)
    num_critics: Annotated[int, Range(1, 1024)] = 2
    lr: Annotated[float, Range(0, 1)] = 3e-4
    discount: Annotated[float, Range(0, 1)] = 0.99
    tau: Annotated[float, Range(0, 1)] = 0.005
    init_temp: Annotated[float, Range(1e-8, 1e4)] = 0.1
    eval_every_s: Annotated[float, Range(0, 10**7)] = 30.0
    checkpoint_every_s: Annotated[float, Range(0, 10**7)] = 60.0
    progress: bool = True
    eval_maze: str = ""
    """only evaluate: the waypoint controller with the actor (--actor, default the shipped one)
    from the evaluation start to the evaluation goal of this maze (umaze, medium, large)"""
    actor: str = ""
    """actor .npz for --eval-maze (default: the shipped assets/ant_goal_actor.npz)"""
    episodes: Annotated[int, Range(1, 1_000)] = 20
    """episodes for --eval-maze"""
    action_noise: Annotated[float, Range(0, 10)] = 0.0
    """Gaussian action noise for --eval-maze (the data use 0.2)"""


def sac_config(cfg: AntTrainConfig):
    from botorl.agents.sac import SACConfig  # lazy: JAX; the spawned simulation workers import this module

    return SACConfig(
        actor_hidden_dims=tuple(cfg.hidden), critic_hidden_dims=tuple(cfg.hidden), actor_layer_norm=True,
        critic_layer_norm=True, num_critics=cfg.num_critics, num_min_critics=cfg.num_critics,
        subsample_replace=False, actor_objective="min", actor_lr=cfg.lr, critic_lr=cfg.lr, temp_lr=cfg.lr,
        discount=cfg.discount, tau=cfg.tau, init_temp=cfg.init_temp, backup_entropy=True,
        chunk_rows=0,
    )


# ------------------------------------------------------------------ simulation workers
# The fields of a transition (the replay buffer's) and the shape of one row of each.
FIELDS = (("observations", (OBS_DIM,)), ("actions", (ACTION_DIM,)), ("rewards", ()), ("next_observations", (OBS_DIM,)),
          ("dones", ()))


class _Ants:
    """Ants plus the per-ant episode bookkeeping; ``collect`` runs ``steps`` steps."""

    def __init__(self, n: int, seed: int, index: int = 0):
        self.index = index  # worker index: each worker evaluates different ants
        self.sim = AntGoalSim(n, seed)
        self.rng = np.random.default_rng(seed + 7919)
        self.ep_return = np.zeros(n)

    def collect(self, params, steps: int, random: bool):
        sim, n = self.sim, self.sim.n
        actor = None if random else NumpyActor(params)
        out = {k: np.empty((steps, n) + s, np.float32) for k, s in FIELDS}
        finished: list[float] = []  # returns of the episodes that ended
        for t in range(steps):
            obs = sim.obs.copy()
            act = self.rng.uniform(-1, 1, (n, ACTION_DIM)) if actor is None else actor(obs, self.rng)
            nobs, rew, term, trunc, _ = sim.step(act)
            out["observations"][t], out["actions"][t], out["rewards"][t] = obs, act, rew
            out["next_observations"][t], out["dones"][t] = nobs, term
            self.ep_return += rew
            for i in np.flatnonzero(term | trunc):
                finished.append(float(self.ep_return[i]))
                self.ep_return[i] = 0.0
        return {k: v.reshape((steps * n,) + v.shape[2:]) for k, v in out.items()}, finished

    def evaluate(self, params, episodes_steps: int, seed: int):
        """Deterministic actor on fresh ants for ``episodes_steps`` steps: goals reached per
        ant and the mean return per step."""
        sim = AntGoalSim(self.sim.n, seed + 1_000 * self.index, horizon=episodes_steps + 1)
        actor = NumpyActor(params)
        reached, ret, falls = np.zeros(sim.n), 0.0, 0
        for _ in range(episodes_steps):
            _, rew, term, _, got = sim.step(actor(sim.obs))
            reached += got
            ret += float(rew.sum())
            falls += int(term.sum())
        return reached.tolist(), ret / (episodes_steps * sim.n), falls


def _worker(conn, n: int, seed: int, index: int):
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    ants = _Ants(n, seed, index)
    while (msg := conn.recv())[0] != "stop":  # (method name, arguments)
        conn.send(getattr(ants, msg[0])(*msg[1:]))


class Collector:
    def __init__(self, num_workers: int, envs_per_worker: int, seed: int):
        self.procs, self.conns, self.local = [], [], None
        if num_workers <= 0:
            self.local = _Ants(envs_per_worker, seed)
            return
        ctx = mp.get_context("spawn")  # no fork of a process that holds a JAX runtime
        for w in range(num_workers):
            a, b = ctx.Pipe()
            p = ctx.Process(target=_worker, args=(b, envs_per_worker, seed * 1000 + w, w), daemon=True)
            p.start()
            self.procs.append(p)
            self.conns.append(a)

    def send(self, method: str, *args):
        """Calls ``method(*args)`` of every worker's ants (in-process: when ``recv`` asks)."""
        if self.local is None:
            for c in self.conns:
                c.send((method, *args))
        else:
            self._pending = partial(getattr(self.local, method), *args)

    def recv(self):
        return [self._pending()] if self.local is not None else [c.recv() for c in self.conns]

    def close(self):
        for c in self.conns:
            with contextlib.suppress(OSError):  # a worker that is gone (BrokenPipeError)
                c.send(("stop",))
        for p in self.procs:
            p.join(timeout=5)


# ------------------------------------------------------------------ the device side


def export_actor(params: dict, path: str | os.PathLike, meta: dict | None = None) -> Path:
    out = io.BytesIO()
    np.savez_compressed(out, **params, meta_json=np.asarray(json.dumps(meta or {})))
    return atomic_write_bytes(path, out.getvalue())


CURVE_FIELDS = ["env_steps", "updates", "seconds", "eval_goals_per_1000", "eval_return_per_step", "eval_falls",
                "train_episode_return", "temperature", "critic_loss"]


def _csv_line(row: list) -> str:
    buf = io.StringIO()
    csv.writer(buf).writerow(row)
    return buf.getvalue()


def train(cfg: AntTrainConfig) -> dict:
    """Train (or continue training) the goal-reaching ant; returns the final state dict."""
    # lazy: JAX; the spawned simulation workers import this module, and need none
    import jax

    from botorl.agents import agent_file, sac

    def host_actor(agent) -> dict:
        return actor_arrays(jax.device_get(agent.actor.params), agent.config.log_std_min, agent.config.log_std_max)

    @partial(jax.jit, donate_argnums=0)  # the buffer is updated in place, not copied
    def insert(buf, new, ptr):
        return {k: jax.lax.dynamic_update_slice_in_dim(buf[k], new[k], ptr, 0) for k in buf}

    @jax.jit
    def train_step(agent, buf, size, key):
        def body(a, k):
            idx = jax.random.randint(k, (cfg.batch_size,), 0, size)
            batch = {n: v[idx] for n, v in buf.items()}
            batch["mc_returns"] = jax.numpy.zeros_like(batch["rewards"])
            return a.train_step(batch)

        agent, metrics = jax.lax.scan(body, agent, jax.random.split(key, cfg.updates_per_iter))
        return agent, {k: v[-1] for k, v in metrics.items()}

    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    agent = sac.SACAgent.create(sac_config(cfg), OBS_DIM, ACTION_DIM, seed=cfg.seed)
    state = {"env_steps": 0, "updates": 0, "seconds": 0.0, "calls": 0, "config": dataclasses.asdict(cfg)}
    resumed = (out / "agent.ckpt").exists() and (out / "state.json").exists()
    if resumed:
        agent = agent_file.load(out / "agent.ckpt", like=agent)
        state.update({k: v for k, v in json.loads((out / "state.json").read_text()).items() if k != "config"})
        print(f"resuming from {out}: {state['env_steps']:,} env steps, {state['updates']:,} updates", flush=True)
    state["calls"] += 1
    curve_path = out / "curve.csv"
    if not curve_path.exists():
        append_text(curve_path, _csv_line(CURVE_FIELDS))

    chunk = max(cfg.num_workers, 1) * cfg.envs_per_worker * cfg.rollout_len  # env steps per iteration
    capacity = max(chunk, (cfg.buffer_size // chunk) * chunk)
    buf = {k: jax.numpy.zeros((capacity,) + s, jax.numpy.float32) for k, s in FIELDS}
    collector = Collector(cfg.num_workers, cfg.envs_per_worker, cfg.seed * 7_919 + state["calls"])
    key = jax.random.fold_in(jax.random.PRNGKey(cfg.seed), state["calls"])
    ptr = size = 0
    t0 = time.time()
    base_seconds = state["seconds"]
    last_ckpt = last_eval = time.time()
    returns: list[float] = []
    metrics = {}
    params = host_actor(agent)
    bar = tqdm(total=cfg.total_env_steps, initial=state["env_steps"], unit="step", desc="train-ant", mininterval=5.0,
               disable=not cfg.progress)

    def save():
        agent_file.save(out / "agent.ckpt", agent)
        state["seconds"] = base_seconds + time.time() - t0
        atomic_write_json(out / "state.json", state, indent=1)
        export_actor(params, out / "actor.npz", {"env_steps": state["env_steps"], "updates": state["updates"],
                                                 "hidden": list(cfg.hidden)})

    def evaluate():
        collector.send("evaluate", params, HORIZON, 12345)
        goals, rets, falls = zip(*collector.recv())  # per worker
        row = [state["env_steps"], state["updates"], round(base_seconds + time.time() - t0, 1),
               round(float(np.mean(sum(goals, []))), 3), round(float(np.mean(rets)), 3), int(sum(falls)),
               round(float(np.mean(returns)), 1) if returns else "",
               round(float(metrics.get("temperature", float("nan"))), 5) if metrics else "",
               round(float(metrics.get("critic_loss", float("nan"))), 4) if metrics else ""]
        append_text(curve_path, _csv_line(row))  # never through a link (botorl/io.py)
        print("eval " + " ".join(f"{k}={v}" for k, v in zip(CURVE_FIELDS, row)), flush=True)
        returns.clear()

    def settle():
        """The updates dispatched last, if any: wait for them, count them, and take their actor."""
        nonlocal agent, metrics, params, pending
        if pending is not None:
            agent, metrics = pending[0], {k: float(v) for k, v in pending[1].items()}
            state["updates"] += cfg.updates_per_iter
            params, pending = host_actor(agent), None

    pending = None
    try:
        warm = 0
        collector.send("collect", params, cfg.rollout_len, not resumed)
        while state["env_steps"] < cfg.total_env_steps:
            results = collector.recv()
            new = {k: np.concatenate([r[0][k] for r in results]) for k in results[0][0]}
            for r in results:
                returns.extend(r[1])
            state["env_steps"] += chunk
            warm += chunk
            settle()  # the updates dispatched last iteration are done by now
            buf = insert(buf, {k: jax.numpy.asarray(v) for k, v in new.items()}, ptr)
            ptr = (ptr + chunk) % capacity
            size = min(size + chunk, capacity)
            ready = warm >= cfg.start_steps
            # Next rollout with the current actor runs while the device updates.
            collector.send("collect", params, cfg.rollout_len, (not ready) and not resumed)
            if ready:
                key, k = jax.random.split(key)
                pending = train_step(agent, buf, size, k)
            bar.update(chunk)
            now = time.time()
            if now - last_eval >= cfg.eval_every_s and metrics:
                collector.recv()  # finish the rollout in flight before the evaluation
                settle()
                evaluate()
                last_eval = time.time()
                collector.send("collect", params, cfg.rollout_len, False)
            if now - last_ckpt >= cfg.checkpoint_every_s:
                settle()
                save()
                last_ckpt = time.time()
            if cfg.time_limit_s and now - t0 >= cfg.time_limit_s:
                print(f"time limit reached after {now - t0:.0f} s", flush=True)
                break
        collector.recv()
        settle()
        evaluate()
        save()
    finally:
        bar.close()
        collector.close()
    try:
        plot_curve(curve_path, out / "curve.png")
    except Exception as err:  # a missing matplotlib must not lose the training
        print(f"(no curve.png: {err})")
    return state


def plot_curve(csv_path, png_path) -> None:
    plt = pyplot()
    rows = list(csv.DictReader(open(csv_path)))
    if not rows:
        return
    x = np.array([float(r["env_steps"]) for r in rows]) / 1e6
    g = np.array([float(r["eval_goals_per_1000"]) for r in rows])
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(x, g, marker=".")
    ax.set_xlabel("environment steps (millions)")
    ax.set_ylabel("goals reached per 1,000 steps\n(deterministic actor)")
    ax.set_title(f"goal-reaching ant, SAC ({float(rows[-1]['updates']) / 1e6:.2f}M updates, "
                 f"{float(rows[-1]['seconds']):.0f} s)")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    atomic_save_figure(fig, png_path, dpi=110)


def main(argv: list[str]) -> int:
    import tyro  # lazy: `python -m` this file (below) runs without the CLI's dependencies

    cfg = tyro.cli(AntTrainConfig, args=argv, prog="botorl train-ant",
                   description="Train the goal-reaching ant with SAC (resumable: rerun with the same --out).")
    check_ranges(cfg)
    if cfg.eval_maze:
        # lazy: --eval-maze only; `python -m` this file (below) runs without the CLI's dependencies
        from botorl.data.generators.antmaze import evaluate_controller, load_actor

        t0 = time.time()
        res = evaluate_controller(cfg.eval_maze, cfg.episodes, cfg.seed, actor=load_actor(cfg.actor or None),
                                  action_noise=cfg.action_noise, progress=cfg.progress)
        print(json.dumps(res))
        print(f"success {res['success']:.2f} over {cfg.episodes} episodes ({time.time() - t0:.0f} s)")
        return 0
    setup_jax()
    state = train(cfg)
    print(f"done: {state['env_steps']:,} env steps, {state['updates']:,} updates, {state['seconds']:.0f} s; "
          f"actor: {Path(cfg.out) / 'actor.npz'}")
    return 0


if __name__ == "__main__":  # used on machines without the botorl CLI's dependencies
    import sys

    kw = {}
    for a in sys.argv[1:]:
        k, v = a.lstrip("-").split("=", 1)
        f = {f.name: f for f in dataclasses.fields(AntTrainConfig)}[k.replace("-", "_")]
        kw[f.name] = (tuple(int(x) for x in v.split(",")) if f.name == "hidden" else
                      (v.lower() in ("1", "true")) if f.type in (bool, "bool") else type(f.default)(v))
    print(json.dumps(train(AntTrainConfig(**kw)), default=str)[:2000])

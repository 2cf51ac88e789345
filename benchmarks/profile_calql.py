"""Where the time of a Cal-QL step goes, and what the proposed fast paths would buy.

    python benchmarks/profile_calql.py [--critics 2] [--hidden 256,256] [--json out.json]

Every figure is median updates (or calls) per second of a jitted function after
compilation, measured in rounds that interleave all the pieces (the machine is shared, so
only ratios within one run mean anything); GFLOP/s use the jaxpr FLOP count of
botorl.benchmarks.flops and the peak is a jitted 1024^2 fp32 matmul in the same run.

Pieces of one Cal-QL update (CQLAgent, calql=True, fixed CQL weight, batch 256):
  full        agent.update(batch): critic step + actor step + temperature step
  critic      agent.critic_step: target (max backup) + grad of the CQL loss + Adam + Polyak
  target      agent.target_values: 10 next actions through the 2-critic target subset
  penalty_fwd the CQL penalty forward only (31 actions per state, all members, one pass)
  critic_grad grad of the critic loss (target given)
  actor       agent.actor_step + temp_step
  core        the critic ensemble forward + backward on the 31 x 256 rows alone (plain
              squared loss): the matmul work without sampling / logsumexp / Adam
  core_noln   the same without LayerNorm
  dense_chain a plain (7936, in) x (in, N*H) ... chain with the same FLOPs as `core`
              but one fat matmul per layer: what the matmul unit does at this size
Plus: dispatch overhead (update_many K=8 vs 8 x update), host-sampled training loop
(ReplayBuffer.sample + update) vs the device-sampled scan prototype
(botorl.agents.common.update_many_on_device), and a recompilation check.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np


def _rate(fn, n: int) -> float:
    t0 = time.perf_counter()
    out = None
    for _ in range(n):
        out = fn()
    jax.block_until_ready(out)
    return n / (time.perf_counter() - t0)


def _calls_for(fn, min_time: float) -> int:
    jax.block_until_ready(fn())  # compile
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    dt = max(time.perf_counter() - t0, 1e-6)
    return max(1, int(min_time / dt))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--critics", type=int, default=2)
    p.add_argument("--hidden", default="256,256")
    p.add_argument("--obs-dim", type=int, default=29)
    p.add_argument("--action-dim", type=int, default=8)
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--min-time", type=float, default=1.0)
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)

    from botorl.jaxsetup import setup_jax

    setup_jax()
    from botorl.agents.cql import CQLAgent, CQLConfig
    from botorl.agents.common import update_many_on_device
    from botorl.benchmarks.flops import jaxpr_flops, matmul_peak_gflops
    from botorl.benchmarks.workloads import make_batch
    from botorl.data.replay import ReplayBuffer

    hidden = tuple(int(h) for h in args.hidden.split(","))
    O, A, B, N = args.obs_dim, args.action_dim, args.batch, args.critics
    cfg = CQLConfig(actor_hidden_dims=(256, 256), critic_hidden_dims=hidden, num_critics=N,
                    calql=True, cql_lagrange=False, max_target_backup=True, num_backup_actions=10,
                    cql_n_actions=10)
    agent = CQLAgent.create(cfg, O, A, 0)
    batch = make_batch(B, O, A)
    key = jax.random.PRNGKey(1)
    m = 3 * cfg.cql_n_actions + 1
    rows = B * m

    # ---- the pieces, each a jitted function of (agent, batch) -> something
    def critic_only(ag, b):
        return ag.critic_step(b, key)[0]

    def target_only(ag, b):
        return ag.target_values(b, key)[0]

    def penalty_fwd(ag, b):
        return ag.cql_penalty(ag.critic.params, b, key)[0]

    target = jax.jit(target_only)(agent, batch)

    def critic_grad(ag, b):
        return jax.grad(lambda p: ag.critic_loss(p, b, target, key)[0])(ag.critic.params)

    def actor_only(ag, b):
        ag, info = ag.actor_step(b, key)
        return ag.temp_step(info["entropy"])[0]

    obs_rep = jnp.repeat(batch["observations"], m, axis=0)
    acts = jax.random.uniform(key, (rows, A), minval=-1, maxval=1)
    y = jnp.zeros((rows,))

    def core_fn(ag, params=None):
        def loss(p):
            return jnp.mean((ag.critic_values(p, obs_rep, acts) - y[None]) ** 2)
        return jax.grad(loss)(ag.critic.params)

    agent_noln = CQLAgent.create(dataclasses.replace(cfg, critic_layer_norm=False), O, A, 0)

    # dense chain with the shapes of the ensemble's layers, members side by side (N*H wide
    # first layer, then block-diagonal work done as N independent matmuls would be... the
    # fair best case is one fat matmul per layer of the same FLOPs).
    dims = [O + A] + list(hidden)
    ws = [jax.random.normal(key, (dims[i], N * dims[i + 1])) * 0.05 for i in range(len(hidden))]
    ws_in = [ws[0]] + [jax.random.normal(key, (N * dims[i], dims[i + 1])) * 0.05 for i in range(1, len(hidden))]
    x0 = jnp.concatenate([obs_rep, acts], axis=1)

    def dense_chain(ws_in):
        def loss(ws_in):
            h = x0
            for w in ws_in:
                h = jax.nn.relu(h @ w)
            return jnp.mean(h**2)
        return jax.grad(loss)(ws_in)

    pieces = {
        "full": (lambda ag, b: ag.update(b)[0], (agent, batch)),
        "critic": (critic_only, (agent, batch)),
        "target": (target_only, (agent, batch)),
        "penalty_fwd": (penalty_fwd, (agent, batch)),
        "critic_grad": (critic_grad, (agent, batch)),
        "actor": (actor_only, (agent, batch)),
        "core": (core_fn, (agent,)),
        "core_noln": (core_fn, (agent_noln,)),
        "dense_chain": (dense_chain, (ws_in,)),
    }
    flops = {}
    calls = {}
    jitted = {}
    for name, (fn, fargs) in pieces.items():
        f = jax.jit(fn)
        jitted[name] = (lambda f=f, fargs=fargs: f(*fargs))
        flops[name] = jaxpr_flops(fn, *fargs).flops
        calls[name] = _calls_for(jitted[name], args.min_time)
        print(f"compiled {name}: {flops[name] / 1e6:.1f} MFLOP", file=sys.stderr, flush=True)

    # ---- dispatch overhead: K updates under one scan vs K calls
    K = 8
    batches = jax.tree_util.tree_map(lambda x: jnp.stack([x] * K), batch)
    state = {"a": agent}

    def many():
        state["a"], _ = state["a"].update_many(batches)
        return state["a"]

    def single_k():
        a = state["a"]
        for _ in range(K):
            a, _ = a.update(batch)
        state["a"] = a
        return a

    # ---- host-sampled loop vs device-sampled scan
    data_rows = 100_000
    big = jax.device_get(make_batch(data_rows, O, A, seed=3))
    buf = ReplayBuffer(data_rows, O, A)
    buf.insert_batch(big["observations"], big["actions"], big["rewards"], big["next_observations"],
                     big["dones"], big["mc_returns"])
    nprng = np.random.default_rng(0)
    dev = jax.tree_util.tree_map(jnp.asarray, big)

    def host_loop():
        a = state["a"]
        for _ in range(K):
            a, _ = a.update(buf.sample(nprng, B))
        state["a"] = a
        return a

    keys = {"k": jax.random.PRNGKey(5)}

    def device_scan():
        keys["k"], sub = jax.random.split(keys["k"])
        state["a"], _ = update_many_on_device(state["a"], dev, sub, K, B)
        return state["a"]

    def sample_only():
        return jax.device_put(buf.sample(nprng, B))

    loops = {"update_many_k8": many, "update_x8": single_k, "host_sampled_x8": host_loop,
             "device_scan_k8": device_scan, "host_sample_only": sample_only}
    for name, fn in loops.items():
        calls[name] = _calls_for(fn, args.min_time)
        jitted[name] = fn

    # ---- recompilation: a fresh agent of the same config, numpy or device batches, must
    # not compile again (XLA compiles are logged by jax_log_compiles)
    import logging

    compiles = []

    class _Count(logging.Handler):
        def emit(self, record):
            if record.getMessage().startswith("Finished XLA compilation"):
                compiles.append(record.getMessage())

    handler = _Count()
    jax_logger = logging.getLogger("jax")
    jax_logger.addHandler(handler)
    old_level = jax_logger.level
    jax_logger.setLevel(logging.DEBUG)
    jax.config.update("jax_log_compiles", True)
    try:
        a2 = CQLAgent.create(cfg, O, A, seed=7)
        for i in range(3):
            b2 = make_batch(B, O, A, seed=9)
            a2, _ = a2.update(jax.device_get(b2) if i == 1 else b2)
        jax.block_until_ready(a2)
    finally:
        jax.config.update("jax_log_compiles", False)
        jax_logger.removeHandler(handler)
        jax_logger.setLevel(old_level)
    recompiles = len([m for m in compiles if "_update" in m])

    samples = {name: [] for name in jitted}
    peaks = []
    for r in range(args.rounds):
        peaks.append(matmul_peak_gflops())
        for name, fn in jitted.items():
            samples[name].append(_rate(fn, calls[name]))
        print(f"round {r + 1}/{args.rounds}", file=sys.stderr, flush=True)
    peak = max(peaks)
    med = {k: statistics.median(v) for k, v in samples.items()}
    out = {"load": os.getloadavg(), "peak_gflops": peak, "critics": N, "hidden": hidden,
           "batch": B, "rows_per_critic_pass": rows, "per_s": med, "flops": flops,
           "recompiles_for_new_agent_same_config": recompiles}
    print(f"load {os.getloadavg()}, matmul peak {peak:.0f} GFLOP/s, Cal-QL {N} x {hidden}, batch {B}")
    print(f"{'piece':18s} {'calls/s':>9s} {'ms/call':>8s} {'MFLOP':>9s} {'GFLOP/s':>8s} {'%peak':>6s} {'% of full':>9s}")
    full_ms = 1e3 / med["full"]
    for name in pieces:
        gf = flops[name] * med[name] / 1e9
        ms = 1e3 / med[name]
        print(f"{name:18s} {med[name]:9.1f} {ms:8.2f} {flops[name] / 1e6:9.1f} {gf:8.1f} {100 * gf / peak:6.1f} {100 * ms / full_ms:9.1f}")
    per_update = {k: med[k] * K for k in ("update_many_k8", "update_x8", "host_sampled_x8", "device_scan_k8")}
    for k, v in per_update.items():
        print(f"{k:18s} {v:9.1f} updates/s ({1e3 / v:.2f} ms/update)")
    print(f"{'host_sample_only':18s} {med['host_sample_only']:9.1f} batches/s ({1e3 / med['host_sample_only']:.2f} ms/batch)")
    print(f"XLA compilations of the update for a new agent of the same config (3 calls, numpy and device batches): {recompiles}")
    out["per_update"] = per_update
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2, default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""One online step's jitted calls: the UTD update and the next action as two dispatches
(``AP.update`` then ``AP.sample``, fine-tuning before issue 41) against one
(``AP.update_then_sample``, fine-tuning now).

    python benchmarks/online_dispatch.py [--size quick|full] [--members 1,8] [--steps 200] [--rounds 5] [--json PATH]

Both are timed in the same process, rounds interleaved, on host batches as fine-tuning gives
them (a fresh (N, u*B, ...) batch per step from a numpy generator, the actions fetched back
every step), at the quick profile's pointmaze size (``quick``: actor and 4 critics of 2 x 64,
batch 4 x 256) or the paper's antmaze size (``full``: actor 2 x 256, 10 critics of 4 x 256,
batch 4 x 256, obs 29, action 8). The two give the same agents and actions bit for bit
(checked before timing). On a CPU the step is the update, so the ratio is near 1 at ``full``;
the dispatch saved matters where a step is short (small networks, an accelerator).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import jax
import numpy as np

from botorl.agents import population as AP
from botorl.agents.sac import SACAgent, SACConfig
from botorl.jaxsetup import setup_jax


UTD = 4


def _batch(rng, n, obs, act, rows=256):
    """Each of ``n`` members' update at UTD 4: 4 critic minibatches of ``rows``, (n, 4, rows, ...)."""
    lead = (n, UTD, rows)
    return {"observations": rng.normal(size=lead + (obs,)).astype(np.float32),
            "actions": rng.uniform(-0.9, 0.9, lead + (act,)).astype(np.float32),
            "rewards": rng.normal(size=lead).astype(np.float32),
            "next_observations": rng.normal(size=lead + (obs,)).astype(np.float32),
            "dones": np.zeros(lead, np.float32), "mc_returns": np.zeros(lead, np.float32)}


def two_calls(agents, batch, obs):
    agents, _ = AP.update(agents, batch)
    actions, agents = AP.sample(agents, obs)
    return agents, jax.device_get(actions)


def one_call(agents, batch, obs):
    agents, _, actions, rng = AP.update_then_sample(agents, batch, obs)
    return agents.replace(rng=rng), jax.device_get(actions)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", choices=("full", "quick"), default="quick")
    p.add_argument("--members", default="1,8")
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    setup_jax()
    if args.size == "full":
        cfg, O, A = SACConfig(actor_hidden_dims=(256, 256), critic_hidden_dims=(256,) * 4, num_critics=10), 29, 8
    else:
        cfg, O, A = SACConfig(actor_hidden_dims=(64, 64), critic_hidden_dims=(64, 64), num_critics=4), 4, 2
    out = {"size": args.size, "backend": jax.default_backend(), "jax": jax.__version__, "rows": []}
    print(f"online step, {args.size} size, UTD {UTD}, {jax.default_backend()} ({jax.device_count()} devices)")
    print(f"{'members':>7s} {'2 calls ms/step':>16s} {'1 call ms/step':>15s} {'speed-up':>9s}")
    for n in (int(m) for m in args.members.split(",")):
        start = AP.stack([SACAgent.create(cfg, O, A, seed=s) for s in range(n)])
        rng = np.random.default_rng(0)
        batches = [_batch(rng, n, O, A) for _ in range(4)]
        obs = [rng.normal(size=(n, O)).astype(np.float32) for _ in range(4)]
        # the same numbers, bit for bit, and every program compiled before timing
        a2, x2 = two_calls(start, batches[0], obs[0])
        a1, x1 = one_call(start, batches[0], obs[0])
        same = np.array_equal(x1, x2) and all(np.array_equal(u, v) for u, v in zip(jax.tree_util.tree_leaves(a1),
                                                                                  jax.tree_util.tree_leaves(a2)))
        if not same:
            raise SystemExit(f"{n} members: the fused call computed other numbers than the two calls")
        times = {"two": [], "one": []}
        for _ in range(args.rounds):
            for name, step in (("two", two_calls), ("one", one_call)):
                agents = start
                t0 = time.perf_counter()
                for t in range(args.steps):
                    agents, _ = step(agents, batches[t % 4], obs[t % 4])
                jax.block_until_ready(agents)
                times[name].append((time.perf_counter() - t0) / args.steps * 1e3)
        two, one = statistics.median(times["two"]), statistics.median(times["one"])
        print(f"{n:7d} {two:16.2f} {one:15.2f} {two / one:8.2f}x")
        out["rows"].append({"members": n, "two_calls_ms": two, "one_call_ms": one, "speed_up": two / one,
                            "rounds": times})
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

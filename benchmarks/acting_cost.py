"""What one action costs: acting on the whole agent against acting on its ``acting_view``.

    python benchmarks/acting_cost.py [--size full|quick] [--members 1,8] [--calls 2000] [--rounds 5] [--json PATH]

Every env step of the warm-up, of fine-tuning and of an evaluation asks the policy for an
action: one jitted call. botorl used to pass the whole agent (actor, 10 critics, their
targets, every Adam state) into that call and get the whole agent back, so each step
flattened and rebuilt hundreds of arrays to read the actor's few; now the call takes the
agent's ``acting_view`` (actor parameters and rng) and returns actions and the next rng
(``botorl/agents/common.py``). Both are timed here in the same process, rounds interleaved,
at the paper's antmaze size (``full``: WSRL's SAC, actor 2 x 256, 10 critics of 4 x 256,
obs 29, action 8) or the quick profile's on pointmaze (``quick``: actor and 4 critics of
2 x 64, obs 4, action 2), for one agent and for a population of N members (``botorl.agents.population``). The two give the
same actions bit for bit (checked before timing).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from botorl.agents import common as C
from botorl.agents import population as AP
from botorl.agents.sac import SACAgent, SACConfig


def _whole_agent_sample(agent, observations):
    """The old call: the whole agent in, the whole agent out."""
    actions, rng = C.sample_fn(agent, observations)
    return actions, agent.replace(rng=rng)


_old_single = jax.jit(_whole_agent_sample)
_old_population = jax.jit(AP.over_members(_whole_agent_sample, (0, 0), across_cores=False))


def _time(fn, calls: int) -> float:
    t0 = time.perf_counter()
    fn(calls)
    return (time.perf_counter() - t0) / calls * 1e3  # ms per call


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", choices=("full", "quick"), default="full")
    p.add_argument("--members", default="1,8")
    p.add_argument("--calls", type=int, default=2000)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    if args.size == "full":
        cfg, obs_dim, action_dim = SACConfig(actor_hidden_dims=(256, 256), critic_hidden_dims=(256,) * 4, num_critics=10), 29, 8
    else:
        cfg, obs_dim, action_dim = SACConfig(actor_hidden_dims=(64, 64), critic_hidden_dims=(64, 64), num_critics=4), 4, 2
    rows = []
    for n in (int(m) for m in args.members.split(",")):
        agents = [SACAgent.create(cfg, obs_dim=obs_dim, action_dim=action_dim, seed=s) for s in range(n)]
        obs = np.random.default_rng(0).normal(size=(n, obs_dim)).astype(np.float32)
        if n == 1:
            agent, o = agents[0], obs[0:1]

            def old(k, agent=agent, o=o):
                a = agent
                for _ in range(k):
                    act, a = _old_single(a, jnp.asarray(o))
                    np.asarray(act)

            def new(k, agent=agent, o=o):
                a = agent
                for _ in range(k):
                    act, a = a.sample_actions(o)
                    np.asarray(act)

            same = np.array_equal(np.asarray(_old_single(agent, jnp.asarray(o))[0]), np.asarray(agent.sample_actions(o)[0]))
        else:
            pop = AP.stack(agents)

            def old(k, pop=pop):
                a = pop
                for _ in range(k):
                    act, a = _old_population(a, jnp.asarray(obs))
                    np.asarray(act)

            def new(k, pop=pop):
                a = pop
                for _ in range(k):
                    act, a = AP.sample(a, obs)
                    np.asarray(act)

            same = np.array_equal(np.asarray(_old_population(pop, jnp.asarray(obs))[0]), np.asarray(AP.sample(pop, obs)[0]))
        if not same:
            raise SystemExit(f"N={n}: the two calls give different actions")
        old(20), new(20)  # compile and warm
        t_old, t_new = [], []
        for _ in range(args.rounds):
            t_old.append(_time(old, args.calls))
            t_new.append(_time(new, args.calls))
        leaves = len(jax.tree_util.tree_leaves(agents[0]))
        view = len(jax.tree_util.tree_leaves(C.acting_view(agents[0])))
        row = {"members": n, "leaves_whole": leaves, "leaves_view": view,
               "ms_whole": statistics.median(t_old), "ms_view": statistics.median(t_new)}
        row["speedup"] = row["ms_whole"] / row["ms_view"]
        rows.append(row)
    load = [round(x, 2) for x in __import__("os").getloadavg()]
    print(f"acting cost, {args.size} size (jax {jax.__version__} {jax.default_backend()}, load {load}; median of {args.rounds} rounds "
          f"of {args.calls} calls, interleaved)")
    print(f"{'members':>7s} {'leaves whole/view':>18s} {'ms whole':>9s} {'ms view':>8s} {'speed-up':>9s}")
    for r in rows:
        print(f"{r['members']:7d} {r['leaves_whole']:>10d}/{r['leaves_view']:<7d} {r['ms_whole']:9.3f} "
              f"{r['ms_view']:8.3f} {r['speedup']:8.2f}x")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"size": args.size, "load": load, "rows": rows}, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

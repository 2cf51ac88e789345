"""How to lay N members over a CPU: member-updates per second for each layout of one update.

    python benchmarks/population_layouts.py [--workload online] [--members 8] [--groups 2,4]
        [--min-time 5]

The question behind `_across_cores` in botorl/agents/population.py: given N members of
the quick profile and the cores of this machine, is it faster to vmap them (one batched
program), to run them one after another inside one jitted call (`lax.map`), to vmap small
groups in turn, and does splitting them over one JAX CPU device per core help? Every row
runs the same agent update (`--workload`: online = the SAC UTD-4 step, iql / calql = K
pre-training steps under `lax.scan`) on the same batches, in this process; the ratio is
against one member alone (the single run's program) measured first.

Layouts:
  one member          the single run: the update on one unbatched agent
  vmap                all N vmapped on device 0 (botorl before it split members)
  in turn             lax.map over the N members on device 0
  groups of g         lax.map over N/g groups, each vmapped, on device 0
  D devices, in turn  what botorl does: botorl.agents.population.update / update_many
  D devices, groups   shard_map over D devices, groups of g within
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from botorl.jaxsetup import setup_jax  # noqa: E402

setup_jax()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import Mesh, NamedSharding, PartitionSpec  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import population as bench  # noqa: E402  (the population benchmark's sizes and agents)

from botorl.agents import common as C  # noqa: E402
from botorl.benchmarks.workloads import make_batch  # noqa: E402
from botorl.agents import population as P  # noqa: E402


def _grouped(fn, g: int):
    """lax.map over groups of g members; g = 1 runs each member unbatched."""
    def run(agents, batch):
        def rs(x):
            return x.reshape((x.shape[0] // g, g) + x.shape[1:])

        def one(ab):
            if g == 1:
                out = fn(*jax.tree_util.tree_map(lambda x: x[0], ab))
                return jax.tree_util.tree_map(lambda x: x[None], out)
            return jax.vmap(fn)(*ab)

        out = jax.lax.map(one, jax.tree_util.tree_map(rs, (agents, batch)))
        return jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:]), out)
    return run


def _timed(call, agents, per_call: int, min_time: float) -> float:
    a = call(agents)
    a = call(a)
    jax.block_until_ready(a)
    t, calls = time.perf_counter(), 0
    while time.perf_counter() - t < min_time:
        a = call(a)
        calls += 1
    jax.block_until_ready(a)
    return calls * per_call / (time.perf_counter() - t)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--workload", default="online", choices=["online", "iql", "calql"])
    p.add_argument("--members", type=int, default=8)
    p.add_argument("--groups", default="2,4", help="group sizes to try besides 1 and N")
    p.add_argument("--min-time", type=float, default=5.0, help="seconds of timed calls per row")
    args = p.parse_args(argv)
    n, w = args.members, args.workload
    s = bench.SIZES["quick"]
    k = bench.K_PER_CALL[w]
    fn = C.update_fn if w == "online" else C.update_many_fn
    if w == "online":
        batch = make_batch(4 * 256, s["obs"], s["act"], 0, lead=(n,))
        per_member = 1
    else:
        batch = make_batch(256, s["obs"], s["act"], 0, lead=(n, k))
        per_member = k
    batch = C.checked_batch({kk: jnp.asarray(np.asarray(v, np.float32)) for kk, v in batch.items()})
    agents = P.stack(bench._agents(w, "quick", n))
    devices = jax.local_devices()
    print(f"{w}, quick sizes, N = {n}, {len(devices)} CPU device(s) "
          f"(BOTORL_CPU_DEVICES sets them); member-updates/s, ratio to one member")

    one_agent = P.member_of(agents, 0)
    one_batch = jax.tree_util.tree_map(lambda x: x[0], batch)
    single = jax.jit(fn)
    base = _timed(lambda a: single(a, one_batch)[0], one_agent, per_member, args.min_time)
    rows = [("one member", base)]

    def on_device0(run):
        f = jax.jit(run)
        return _timed(lambda a: f(a, batch)[0], agents, n * per_member, args.min_time)

    rows.append(("vmap", on_device0(jax.vmap(fn))))
    groups = sorted({1, *[int(g) for g in args.groups.split(",") if g and n % int(g) == 0]})
    for g in groups:
        rows.append(("in turn" if g == 1 else f"groups of {g}", on_device0(_grouped(fn, g))))
    d = min(len(devices), n)
    if d > 1 and n % d == 0:
        mesh = Mesh(np.array(devices[:d]), ("members",))
        sh = NamedSharding(mesh, PartitionSpec("members"))
        placed_agents, placed_batch = jax.device_put(agents, sh), jax.device_put(batch, sh)
        # in turn on every device: the pipeline's own entry point (botorl.agents.population)
        update = P.update if w == "online" else P.update_many
        rate = _timed(lambda a: update(a, placed_batch)[0], placed_agents, n * per_member, args.min_time)
        rows.append((f"{d} devices, in turn (botorl)", rate))
        for g in [g for g in groups if g > 1 and (n // d) % g == 0]:
            run = jax.jit(jax.shard_map(_grouped(fn, g), mesh=mesh, in_specs=PartitionSpec("members"),
                                        out_specs=PartitionSpec("members"), check_vma=False))
            rate = _timed(lambda a: run(a, placed_batch)[0], placed_agents, n * per_member, args.min_time)
            rows.append((f"{d} devices, groups of {g}", rate))
    for name, rate in rows:
        print(f"  {name:<26} {rate:9.1f}   {rate / base:5.2f}x", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

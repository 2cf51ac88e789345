"""Population throughput: member-updates per second for N members trained as one program.

    python benchmarks/population.py [--sizes quick,full] [--members 1,2,4,8,16]
        [--workloads calql,iql,boto,online] [--min-time 2] [--json PATH]

For each workload and size, N members (seeds 0..N-1) are stacked on a leading axis and
updated with one jitted call (botorl.agents.population); the table gives member-updates/s
(N x updates per call x calls / s) and its ratio to N = 1 measured in the same process.
Batches are fixed random arrays already on the device (the host sampling of the pipeline is
not in these rows; the whole-run rows are `--whole-run`).

Workloads (batch 256 per critic step, as the pipeline's profiles):
  calql   Cal-QL pre-training step, K per call under lax.scan (the pipeline's updates_per_call)
  iql     IQL pre-training step, K per call
  boto    BOTO critic step, K per call, each member with its own alpha
  online  the online SAC step at UTD 4 (4 critic minibatches of 256 + actor on 1,024 rows)

Sizes:
  quick   the quick profile on pointmaze (obs 4, action 2): actor and 4 critics of 2 x 64
          with LayerNorm in every algorithm; Cal-QL/BOTO with 5 CQL samples per kind and no
          max-target backup.
  full    the paper's antmaze settings (obs 29, action 8): WSRL's 10 critics of 4 x 256 and
          actor 2 x 256 in every algorithm (IQL's value net 4 x 256); Cal-QL with 10 CQL
          samples per kind and the max-target backup over 10.

`--whole-run` also times whole quick runs of the main job (BOTO on MAIN_TASK) (`botorl run` subprocesses) as one
member and as N members (`--seeds 0-(N-1)`), and prints the ratio of wall times.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from botorl.jaxsetup import setup_jax  # noqa: E402

setup_jax()

from botorl.agents.cql import CQLAgent, CQLConfig  # noqa: E402
from botorl.agents.iql import IQLAgent, IQLConfig  # noqa: E402
from botorl.agents.sac import SACAgent, SACConfig  # noqa: E402
from botorl.benchmarks.workloads import make_batch  # noqa: E402
from botorl.boto.config import BOTOConfig  # noqa: E402
from botorl.boto.objective import ObjectiveSettings  # noqa: E402
from botorl.configs.schema import RunConfig  # noqa: E402
from botorl.agents import population as P  # noqa: E402
from botorl.boto.objective import population_update_many  # noqa: E402

# Sizes of the pipeline's presets (botorl/configs/presets.py + resolve.py; written out here so
# the script needs no environment packages, e.g. on a GPU machine without gymnasium). Every
# offline algorithm pre-trains the networks and the ensemble that fine-tuning takes over.
SIZES = {
    "quick": dict(obs=4, act=2, hidden=(64, 64), actor=(64, 64), critics=4, n_actions=5, backup=False),
    "full": dict(obs=29, act=8, hidden=(256, 256, 256, 256), actor=(256, 256), critics=10, n_actions=10,
                 backup=True),
}
K_PER_CALL = {"calql": 10, "iql": 50, "boto": 50, "online": 1}


def _fields(cls, **kw):
    import dataclasses

    names = {f.name for f in dataclasses.fields(cls)}
    return cls(**{k: v for k, v in kw.items() if k in names})


def _agents(workload: str, size: str, n: int):
    s = SIZES[size]
    net = dict(actor_hidden_dims=s["actor"], critic_hidden_dims=s["hidden"], num_critics=s["critics"],
               actor_layer_norm=True, critic_layer_norm=True)
    if workload in ("calql", "boto"):
        cfg = _fields(CQLConfig, **net, cql_n_actions=s["n_actions"], max_target_backup=s["backup"],
                      num_backup_actions=s["n_actions"], cql_lagrange=False, calql=True)
        return [CQLAgent.create(cfg, s["obs"], s["act"], seed) for seed in range(n)]
    if workload == "iql":
        cfg = _fields(IQLConfig, **net, value_hidden_dims=s["hidden"])
        return [IQLAgent.create(cfg, s["obs"], s["act"], seed) for seed in range(n)]
    cfg = _fields(SACConfig, **net, max_target_backup=s["backup"], num_backup_actions=s["n_actions"])
    return [SACAgent.create(cfg, s["obs"], s["act"], seed) for seed in range(n)]


def build(workload: str, size: str, n: int, k: int):
    """(step(calls) -> None, member-updates per call)."""
    s = SIZES[size]
    agents = P.stack(_agents(workload, size, n))
    state = {"agents": agents}
    if workload == "online":
        batch = make_batch(256, s["obs"], s["act"], 0, lead=(n, 4))  # UTD 4: 4 minibatches of 256

        def call(a):
            return P.update(a, batch)[0]
        per_call = n
    elif workload == "boto":
        settings = ObjectiveSettings.resolve(BOTOConfig(), P.member_of(agents, 0))
        batches = make_batch(256, s["obs"], s["act"], 0, lead=(n, k))
        batches = {kk: v for kk, v in batches.items() if kk != "mc_returns"}
        alphas = np.linspace(-1, 1, n).astype(np.float32) if n > 1 else np.zeros(1, np.float32)

        def call(a):
            return population_update_many(a, batches, alphas, settings)[0]
        per_call = n * k
    else:
        batches = make_batch(256, s["obs"], s["act"], 0, lead=(n, k))

        def call(a):
            return P.update_many(a, batches)[0]
        per_call = n * k

    def step(calls: int) -> None:
        a = state["agents"]
        for _ in range(calls):
            a = call(a)
        jax.block_until_ready(a)
        state["agents"] = a

    return step, per_call


def measure(workload: str, size: str, n: int, min_time: float, k: int | None = None) -> dict:
    k = K_PER_CALL[workload] if k is None else k
    t0 = time.perf_counter()
    step, per_call = build(workload, size, n, k)
    step(1)  # compile
    compile_s = time.perf_counter() - t0
    # calls per round: about min_time / 3 seconds
    t = time.perf_counter()
    step(1)
    one = max(time.perf_counter() - t, 1e-6)
    calls = max(1, int(min_time / 3 / one))
    rates = []
    for _ in range(3):
        t = time.perf_counter()
        step(calls)
        rates.append(calls * per_call / (time.perf_counter() - t))
    return {"workload": workload, "size": size, "members": n, "updates_per_call": k,
            "member_updates_per_s": float(np.median(rates)), "calls_timed": 3 * calls, "compile_s": compile_s}


MAIN_TASK = RunConfig().task  # botorl run's default task


def whole_run(n: int, extra: list[str], out_root: Path) -> float:
    out = out_root / f"whole-{n}-{int(time.time())}"
    seeds = "0" if n == 1 else f"0-{n - 1}"
    cmd = [sys.executable, "-m", "botorl.cli", "run", "--task", MAIN_TASK, "--method", "boto",
           "--profile", "quick", "--seeds", seeds, "--no-progress", "--out", str(out), *extra]
    t = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sizes", default="quick,full")
    p.add_argument("--members", default="1,2,4,8,16")
    p.add_argument("--workloads", default="calql,iql,boto,online")
    p.add_argument("--min-time", type=float, default=2.0, help="seconds of timed calls per row (3 rounds)")
    p.add_argument("--k", type=int, default=None, help="updates per call for every workload (default: per workload)")
    p.add_argument("--json", default=None)
    p.add_argument("--whole-run", default=None, help="also time whole quick runs: member counts, e.g. 1,8")
    p.add_argument("--whole-run-args", default="", help="extra `botorl run` arguments for --whole-run")
    p.add_argument("--whole-run-out", default="/tmp/botorl-population-bench")
    args = p.parse_args(argv)
    members = [int(x) for x in args.members.split(",")]
    dev = jax.devices()[0]
    print(f"device: {dev.device_kind} ({jax.default_backend()}), {os.cpu_count()} CPUs, {platform.processor() or platform.machine()}")
    rows = []
    print(f"{'workload':<8} {'size':<6} {'N':>3} {'K':>3} {'member-upd/s':>13} {'x N=1':>7} {'compile s':>9}")
    for size in args.sizes.split(","):
        for w in args.workloads.split(","):
            base = None
            for n in members:
                r = measure(w, size, n, args.min_time, args.k)
                if base is None:
                    base = r["member_updates_per_s"] if n == 1 else None
                r["ratio_vs_1"] = (r["member_updates_per_s"] / base) if base else None
                rows.append(r)
                ratio = f"{r['ratio_vs_1']:.2f}" if r["ratio_vs_1"] else "-"
                print(f"{w:<8} {size:<6} {n:>3} {r['updates_per_call']:>3} {r['member_updates_per_s']:>13.1f} "
                      f"{ratio:>7} {r['compile_s']:>9.1f}", flush=True)
                if args.json:  # after every row: a run cut short keeps what it measured
                    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
                    Path(args.json).write_text(json.dumps({"device": dev.device_kind, "rows": rows}, indent=1))
    whole = []
    if args.whole_run:
        extra = args.whole_run_args.split()
        times = {}
        for n in [int(x) for x in args.whole_run.split(",")]:
            times[n] = whole_run(n, extra, Path(args.whole_run_out))
            whole.append({"members": n, "wall_s": times[n], "ratio_vs_1": times[n] / times[min(times)]})
            print(f"whole quick {MAIN_TASK} run, {n} member(s): {times[n]:.1f} s "
                  f"({times[n] / times[min(times)]:.2f}x the wall time of {min(times)})", flush=True)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"device": dev.device_kind, "backend": jax.default_backend(),
                                               "rows": rows, "whole_run": whole}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

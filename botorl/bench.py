"""``botorl bench``: updates per second of each agent's jitted update at the reference sizes.

Each workload is a named entry of ``WORKLOADS``: a function ``(repeats, steps) -> dict``
that builds its agent and batches, compiles once (not timed), then times ``steps`` calls of
the compiled update ``repeats`` times and reports the median. Add a workload (e.g. the
d3rlpy comparison of issue 7) by adding a function to the table.

Shapes: batch 256 (an "online step at UTD 4" uses a 1,024 batch: 4 critic minibatches of
256, then one actor and one temperature update); observation/action sizes of antmaze
(29 / 8). Numbers on a shared machine are indicative only.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np

OBS_DIM, ACTION_DIM, BATCH = 29, 8, 256
ANTMAZE = dict(actor_hidden_dims=(256, 256), critic_hidden_dims=(256, 256, 256, 256))
ADROIT = dict(actor_hidden_dims=(512, 512), critic_hidden_dims=(512, 512, 512))
SMALL = dict(actor_hidden_dims=(256, 256), critic_hidden_dims=(256, 256))


def _batch(rng: np.random.Generator, size: int) -> dict:
    return {
        "observations": rng.normal(size=(size, OBS_DIM)).astype(np.float32),
        "actions": rng.uniform(-1, 1, (size, ACTION_DIM)).astype(np.float32),
        "rewards": rng.normal(size=size).astype(np.float32),
        "next_observations": rng.normal(size=(size, OBS_DIM)).astype(np.float32),
        "dones": (rng.uniform(size=size) < 0.01).astype(np.float32),
        "mc_returns": rng.normal(size=size).astype(np.float32),
    }


def _time_updates(agent, batch_size: int, repeats: int, steps: int) -> dict:
    import jax

    rng = np.random.default_rng(0)
    batch = jax.device_put(_batch(rng, batch_size))
    t0 = time.perf_counter()
    agent, info = agent.update(batch)
    jax.block_until_ready(info)
    compile_s = time.perf_counter() - t0
    rates = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(steps):
            agent, info = agent.update(batch)
        jax.block_until_ready((agent, info))
        rates.append(steps / (time.perf_counter() - t0))
    return {"updates_per_s": statistics.median(rates), "all": rates, "compile_s": compile_s, "steps": steps}


def _sac(n_critics: int, net: dict, utd: int = 1):
    def run(repeats: int, steps: int) -> dict:
        from botorl.agents.sac import SACAgent, SACConfig

        cfg = SACConfig(**net, num_critics=n_critics, utd_ratio=utd)
        return _time_updates(SACAgent.create(cfg, OBS_DIM, ACTION_DIM, 0), BATCH * utd, repeats, steps)

    return run


def _cql(n_critics: int, net: dict, calql: bool):
    def run(repeats: int, steps: int) -> dict:
        from botorl.agents.cql import CQLAgent, CQLConfig

        cfg = CQLConfig(**net, num_critics=n_critics, calql=calql)
        return _time_updates(CQLAgent.create(cfg, OBS_DIM, ACTION_DIM, 0), BATCH, repeats, max(1, steps // 4))

    return run


def _iql(repeats: int, steps: int) -> dict:
    from botorl.agents.iql import IQLAgent, IQLConfig

    return _time_updates(IQLAgent.create(IQLConfig(), OBS_DIM, ACTION_DIM, 0), BATCH, repeats, steps)


def _matmul(repeats: int, steps: int) -> dict:
    """fp32 2048^3 matmul: the machine's speed now, to read the other rows against."""
    import jax
    import jax.numpy as jnp

    x = jnp.ones((2048, 2048), jnp.float32)
    f = jax.jit(lambda a: a @ a)
    f(x).block_until_ready()
    rates = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(steps):
            f(x).block_until_ready()
        rates.append(steps / (time.perf_counter() - t0))
    med = statistics.median(rates)
    return {"updates_per_s": med, "gflops": med * 2 * 2048**3 / 1e9, "all": rates, "compile_s": 0.0, "steps": steps}


# name -> (description, function(repeats, steps) -> result dict)
WORKLOADS: dict[str, tuple[str, Callable[[int, int], dict]]] = {
    "matmul_2048": ("fp32 2048x2048 matmuls/s (reference for the machine's current speed)", _matmul),
    "sac_2x256_2critics": ("SAC update, 2 critics 2x256, batch 256", _sac(2, SMALL)),
    "sac_antmaze_10critics": ("SAC update, 10 critics 4x256, batch 256", _sac(10, ANTMAZE)),
    "sac_adroit_10critics": ("SAC update, 10 critics 3x512, batch 256", _sac(10, ADROIT)),
    "sac_online_step_utd4": ("WSRL online step: 4 critic + 1 actor + 1 temp update, 10 critics 4x256, batch 4x256", _sac(10, ANTMAZE, utd=4)),
    "cql_2x256_2critics": ("CQL update (10+10+10 actions), 2 critics 2x256", _cql(2, SMALL, False)),
    "calql_2x256_2critics": ("Cal-QL update, 2 critics 2x256", _cql(2, SMALL, True)),
    "calql_antmaze_10critics": ("Cal-QL update, 10 critics 4x256 (antmaze pre-training)", _cql(10, ANTMAZE, True)),
    "iql_2x256": ("IQL update, 2 Q + V 2x256, batch 256", _iql),
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--paper" in argv:
        # what a whole paper run costs, from the real pipeline's stages (issue 25)
        from botorl.benchmarks.paper import main as paper_main

        return paper_main(argv)
    if any(a == "--against" or a.startswith("--against=") for a in argv):
        # The side-by-side comparison (issue 7) lives in botorl/benchmarks/.
        from botorl.benchmarks.suite import main as against_main

        return against_main(argv)
    parser = argparse.ArgumentParser(prog="botorl bench", description=__doc__.splitlines()[0])
    parser.add_argument("--json", type=Path, default=None, help="write the results to this JSON file")
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats per workload (median reported)")
    parser.add_argument("--steps", type=int, default=20, help="updates per repeat (CQL workloads use a quarter)")
    parser.add_argument("--only", nargs="*", default=None, help=f"workload names: {', '.join(WORKLOADS)}")
    parser.add_argument("--paper", action="store_true", help="project a whole paper run per task from short windows of the real pipeline (`botorl bench --paper --help`)")
    parser.add_argument("--against", choices=["d3rlpy"], help="compare with d3rlpy in the same run; its own options (--threads, --quick, --min-time, ...): `botorl bench --against d3rlpy --help`")
    args = parser.parse_args(argv)
    from botorl.errors import ConfigError
    from botorl.jaxsetup import setup_jax

    if args.repeats < 1 or args.steps < 1:
        raise ConfigError("botorl bench: --repeats and --steps must be >= 1.")
    names = list(WORKLOADS) if not args.only else args.only
    unknown = [n for n in names if n not in WORKLOADS]
    if unknown:
        raise ConfigError(f"botorl bench: unknown workload(s) {', '.join(unknown)}; choose from {', '.join(WORKLOADS)}.")
    setup_jax()
    import jax

    results = {}
    for name in names:
        desc, fn = WORKLOADS[name]
        res = fn(args.repeats, args.steps)
        res["description"] = desc
        results[name] = res
        print(f"{name:28s} {res['updates_per_s']:9.1f} updates/s   (compile {res['compile_s']:.1f} s)  {desc}", flush=True)
    out = {
        "device": str(jax.devices()[0]),
        "jax": jax.__version__,
        "note": "median of repeats after compilation; shared machine: indicative only",
        "results": results,
    }
    if args.json is not None:
        from botorl.io import atomic_write_bytes

        atomic_write_bytes(args.json, json.dumps(out, indent=2).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())

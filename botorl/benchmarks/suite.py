"""``botorl bench``: botorl's updates timed, and beside d3rlpy's (benchmarks/against_d3rlpy.py).

Per workload (``workloads.WORKLOADS``): botorl updates/s (against d3rlpy: d3rlpy updates/s
on identical shapes and their ratio), botorl's achieved GFLOP/s (FLOPs per update counted on the traced
program, ``flops.jaxpr_flops``; XLA's cost analysis beside it) and its share of the fp32
matmul peak measured in the same run. Then env steps/s of the online loop (UTD 4, 10
critics) and its ratio to the online update alone (``online_loop_efficiency``).

Noise: every number compared is measured in the same run, rounds interleaved (round r times
every workload and its d3rlpy twin before round r + 1), each figure the median over rounds.
"""

from __future__ import annotations

import math
import os
import platform
import statistics
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated, Any, Callable, Optional

import jax
import tyro

from botorl.agents.sac import SACAgent, SACConfig
from botorl.benchmarks import flops as flopmod
from botorl.benchmarks import workloads as wl
from botorl.benchmarks.online_loop import OnlineLoop
from botorl.benchmarks.paper import main as paper_main
from botorl.envs.registry import get_task
from botorl.errors import BotorlError, Range, check_ranges
from botorl.io import atomic_write_json
from botorl.jaxsetup import setup_jax

SCHEMA_VERSION = 1


@dataclass
class BenchConfig:
    """Options of ``botorl bench`` (and of benchmarks/against_d3rlpy.py)."""

    json: Optional[str] = None
    """also write the results to this JSON file"""
    quick: bool = False
    """fewer repeats, shorter timings, a smaller set of workloads"""
    only: Optional[str] = None
    """comma-separated workload names (default: all; --quick: sac2,calql,online_utd4)"""
    repeats: Annotated[int, Range(1, 1000)] = 5
    """interleaved rounds; figures are medians over them"""
    min_time: Annotated[float, Range(0.01, 3600)] = 1.5
    """seconds per timed block"""
    loop: bool = True
    """also time the whole online loop (env + buffer + update)"""
    tiny: bool = False
    """toy network sizes (for tests: compiles in seconds)"""
    threads: Annotated[int, Range(0, 1024)] = 0
    """threads of both sides: 0 = all cores (XLA's and torch's default); 1 = one thread each
    (XLA: no Eigen thread pool; torch.set_num_threads(1)), less hurt by a loaded machine"""


def _load() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def _median(xs: list[float]) -> float | None:
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return statistics.median(xs) if xs else None


def _calibrate(step: Any, min_time: float) -> int:
    """Calls per timed block, after compiling (first call) and warming up."""
    step(1)
    t0 = time.perf_counter()
    step(2)
    per_call = max((time.perf_counter() - t0) / 2, 1e-6)
    return max(1, int(math.ceil(min_time / per_call)))


def _time_block(step: Any, n: int) -> tuple[float, float]:
    """(calls per wall-clock second, calls per CPU second of this process)."""
    t0, c0 = time.perf_counter(), time.process_time()
    step(n)
    return n / (time.perf_counter() - t0), n / max(time.process_time() - c0, 1e-9)


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _options(cfg: BenchConfig) -> tuple[int, float, list[wl.Workload]]:
    """(rounds, seconds per timing, the workloads) of ``cfg``; BotorlError for a bad one."""
    repeats, min_time = (min(cfg.repeats, 2), min(cfg.min_time, 0.5)) if cfg.quick else (cfg.repeats, cfg.min_time)
    if repeats < 1 or min_time <= 0:
        raise BotorlError(f"bench: --repeats ({cfg.repeats}) and --min-time ({cfg.min_time}) must be positive.")
    names = cfg.only.split(",") if cfg.only else list(wl.QUICK if cfg.quick else wl.WORKLOADS)
    if unknown := [n for n in names if n not in wl.WORKLOADS]:
        raise BotorlError(f"bench: unknown workload(s) {', '.join(unknown)} in --only; "
                          f"choose from {', '.join(wl.WORKLOADS)}.")
    return repeats, min_time, [wl.WORKLOADS[n].tiny() if cfg.tiny else wl.WORKLOADS[n] for n in names]


def _prepare(w: wl.Workload) -> tuple[dict[str, Any], wl.Bound]:
    """A workload's row (its shapes and FLOP counts; the timings to come) and its bound update."""
    shapes = {"num_critics": w.num_critics, "critic_hidden": list(w.critic_hidden),
              "actor_hidden": list(w.actor_hidden), "obs_dim": w.obs_dim, "action_dim": w.action_dim,
              "batch": w.batch, "utd": w.utd, "cql_samples_per_kind": w.n_action_samples,
              "updates_per_call": w.scan_k}
    b = wl.build(w)
    k = b.updates_per_call
    count = flopmod.jaxpr_flops(b.flop_fn, *b.flop_args)
    row = {"label": w.label, "note": w.note, "shapes": shapes,
           "botorl_updates_per_s": None, "d3rlpy_updates_per_s": None,
           "ratio": None, "gflops": None, "peak_fraction": None,
           "flops_per_update": count.flops / k, "flops_per_update_xla": None,
           "botorl_samples": [], "d3rlpy_samples": [],
           "botorl_cpu_samples": [], "d3rlpy_cpu_samples": [],
           "matmul_flops_per_update": count.matmul_flops / k, "updates_per_call": k}
    try:
        row["flops_per_update_xla"] = flopmod.xla_flops(b.flop_fn, *b.flop_args) / k
    except Exception as err:  # the cross-check must not sink the run
        row["flops_per_update_xla_error"] = str(err)
    return row, b


def _summarize(row: dict[str, Any], peak: float) -> None:
    """A row's medians over the rounds, its ratios to d3rlpy and its share of the matmul peak."""
    for side in ("botorl", "d3rlpy"):
        row[f"{side}_updates_per_s"] = _median(row[f"{side}_samples"])
        row[f"{side}_updates_per_cpu_s"] = _median(row[f"{side}_cpu_samples"])
    if row["botorl_updates_per_s"] and row["d3rlpy_updates_per_s"]:
        row["ratio"] = row["botorl_updates_per_s"] / row["d3rlpy_updates_per_s"]
        # Per round, then the median: both sides of a round met the same load.
        pairs = [b / d for b, d in zip(row["botorl_samples"], row["d3rlpy_samples"]) if d > 0]
        row["ratio_median_of_rounds"] = _median(pairs)
    if row["botorl_updates_per_cpu_s"] and row["d3rlpy_updates_per_cpu_s"]:
        row["ratio_cpu"] = row["botorl_updates_per_cpu_s"] / row["d3rlpy_updates_per_cpu_s"]
    if row["botorl_updates_per_s"] and row["flops_per_update"]:
        row["gflops"] = row["flops_per_update"] * row["botorl_updates_per_s"] / 1e9
        row["peak_fraction"] = row["gflops"] / peak


def _backend_started() -> bool:
    """Whether JAX's XLA backend has started; True where this JAX does not say."""
    try:
        from jax._src import xla_bridge  # lazy: JAX's private module, so a JAX without it only warns as before
        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):
        return True


def run(cfg: BenchConfig, twin: Callable[[BenchConfig], Any] | None = None) -> dict[str, Any]:
    """``twin``: starts the d3rlpy worker (benchmarks/against_d3rlpy.py) whose same updates are
    timed in the same rounds, once the options are checked."""
    if cfg.threads == 1:
        # XLA reads XLA_FLAGS when its backend starts, not when jax is imported (this module
        # imports it): the flag is too late only once a backend exists (bench called in-process)
        if _backend_started():
            _log("bench: --threads 1 must be set before JAX starts; XLA keeps its threads")
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                                   " --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1").strip()
    setup_jax()
    repeats, min_time, chosen = _options(cfg)
    worker = None if twin is None else twin(cfg)

    load_start = _load()
    _log(f"bench: {len(chosen)} workloads x {repeats} rounds of {min_time:.1f} s; load {load_start}")
    rows: dict[str, dict[str, Any]] = {}
    timed: dict[str, tuple[wl.Bound, int]] = {}  # the bound update and its calls per timed block
    for w in chosen:
        rows[w.name], b = _prepare(w)
        timed[w.name] = b, _calibrate(b.step, min_time)
        if worker is not None and w.d3rlpy_algo is not None and (err := worker.setup(w)):
            rows[w.name]["d3rlpy_error"] = err

    peaks: list[float] = []
    for r in range(repeats):
        peaks.append(flopmod.matmul_peak_gflops())
        for w in chosen:
            row, (b, calls) = rows[w.name], timed[w.name]
            wall, cpu = _time_block(b.step, calls)
            row["botorl_samples"].append(wall * b.updates_per_call)
            row["botorl_cpu_samples"].append(cpu * b.updates_per_call)
            if worker is not None and w.d3rlpy_algo is not None and "d3rlpy_error" not in row:
                try:
                    wall, cpu = worker.time(w.name, min_time)
                    row["d3rlpy_samples"].append(wall)
                    row["d3rlpy_cpu_samples"].append(cpu)
                except RuntimeError as err:
                    row["d3rlpy_error"] = str(err)
        _log(f"bench: round {r + 1}/{repeats} done")

    online = next((w for w in chosen if w.name == "online_utd4"), None)  # --tiny: its tiny form
    loop = _loop_benchmark(online, repeats, min_time) if cfg.loop and online else None
    if worker is not None:
        worker.close()

    peak = max(peaks)
    for w in chosen:  # rows that share another row's d3rlpy update (same round, same figures)
        if (same := rows.get(w.d3rlpy_same_as or "")) is not None:
            rows[w.name].update(d3rlpy_samples=list(same["d3rlpy_samples"]),
                                d3rlpy_cpu_samples=list(same["d3rlpy_cpu_samples"]), d3rlpy_same_as=w.d3rlpy_same_as)
    for row in rows.values():
        _summarize(row, peak)

    machine = {"platform": platform.platform(), "cpu_count": os.cpu_count(), "jax": jax.__version__,
               "jax_backend": jax.default_backend(), "load_start": load_start, "load_end": _load()}
    if worker is not None:
        machine["d3rlpy_worker"] = {k: v for k, v in worker.info.items() if k != "ready"}
    return {
        "schema": SCHEMA_VERSION,
        "command": ("python benchmarks/against_d3rlpy.py" if worker else "botorl bench") + (" --quick" if cfg.quick else ""),
        "machine": machine,
        "settings": {"repeats": repeats, "min_time_s": min_time, "tiny": cfg.tiny,
                     "flop_count": "jaxpr (dot_general exact, elementwise 1/elem, scan x length); "
                                   "flops_per_update_xla = XLA cost analysis (counts a scan body once)"},
        "matmul_peak_gflops": peak,
        "matmul_peak_samples": peaks,
        "updates": rows,
        "online_loop": loop,
        "online_loop_efficiency": None if loop is None else loop["online_loop_efficiency"],
    }


def _loop_benchmark(w: wl.Workload, repeats: int, min_time: float) -> dict[str, Any]:
    """The online loop and the same update alone, interleaved round by round."""
    spec = get_task("antmaze-large-diverse-v2")
    obs_dim, action_dim = spec.obs_dim, spec.action_dim
    agent = SACAgent.create(SACConfig(actor_hidden_dims=w.actor_hidden, critic_hidden_dims=w.critic_hidden,
                                      num_critics=w.num_critics), obs_dim, action_dim, 0)
    loop = OnlineLoop(agent, spec, w.batch, w.utd, prefill=max(w.batch * w.utd, 2000))
    # The update alone on the env's shapes (the same jit cache entry as the table's row
    # when those are the same).
    alone = wl.build(replace(w, obs_dim=obs_dim, action_dim=action_dim))
    with loop.state:  # closes the loop's envs
        n_loop = _calibrate(loop.run, min_time)
        n_alone = _calibrate(alone.step, min_time)
        loop_rates, alone_rates = [], []
        for _ in range(repeats):
            loop_rates.append(_time_block(loop.run, n_loop)[0])
            alone_rates.append(_time_block(alone.step, n_alone)[0])
    return {"env": spec.name, "obs_dim": obs_dim, "action_dim": action_dim,
            "env_steps_per_s": _median(loop_rates), "samples": loop_rates,
            "update_alone_per_s": _median(alone_rates), "update_alone_samples": alone_rates,
            "online_loop_efficiency": _median([lr / ar for lr, ar in zip(loop_rates, alone_rates)])}


def _fmt(x: Any, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def format_table(result: dict[str, Any]) -> str:
    m = result["machine"]
    lines = [f"botorl bench  (jax {m['jax']} {m['jax_backend']}, {m['cpu_count']} cores, "
             f"load {m['load_start']} -> {m['load_end']}"
             + (f"; d3rlpy {m['d3rlpy_worker'].get('d3rlpy')} torch {m['d3rlpy_worker'].get('torch')}"
                f" x{m['d3rlpy_worker'].get('torch_threads')} threads" if "d3rlpy_worker" in m else "") + ")",
             f"fp32 matmul peak (1024^2, jitted, best of {len(result['matmul_peak_samples'])}): "
             f"{result['matmul_peak_gflops']:.0f} GFLOP/s"]
    head = (f"{'update':34s} {'botorl/s':>9s} {'d3rlpy/s':>9s} {'ratio':>6s} {'ratio_cpu':>9s} "
            f"{'MFLOP/upd':>10s} {'GFLOP/s':>8s} {'%peak':>6s}")
    lines += [head, "-" * len(head)]
    for name, r in result["updates"].items():
        lines.append(f"{r['label'][:34]:34s} {_fmt(r['botorl_updates_per_s'], '9.1f')} "
                     f"{_fmt(r['d3rlpy_updates_per_s'], '9.1f')} {_fmt(r['ratio'], '6.2f')} "
                     f"{_fmt(r.get('ratio_cpu'), '9.2f')} "
                     f"{_fmt(r['flops_per_update'] and r['flops_per_update'] / 1e6, '10.1f')} "
                     f"{_fmt(r['gflops'], '8.1f')} {_fmt(r['peak_fraction'] and 100 * r['peak_fraction'], '6.1f')}")
        if "d3rlpy_error" in r:
            lines.append(f"    d3rlpy: {r['d3rlpy_error']}")
    loop = result.get("online_loop")
    if loop:
        lines.append(f"online loop ({loop['env']}, UTD 4, 10 critics): {loop['env_steps_per_s']:.1f} env steps/s, "
                     f"update alone {loop['update_alone_per_s']:.1f}/s (interleaved); "
                     f"online_loop_efficiency = {_fmt(result['online_loop_efficiency'], '.2f')}")
    lines.append("ratio = botorl/d3rlpy wall-clock updates/s; ratio_cpu = the same per CPU-second of each "
                 "process (less sensitive to other users' load); %peak = GFLOP/s over the matmul peak")
    return "\n".join(lines)


def write_json(result: dict[str, Any], path: str) -> None:
    """Atomically (temp file + rename): an interrupted run leaves no half file."""
    atomic_write_json(Path(path).expanduser(), result, exact=True)


def main(argv: list[str] | None = None, twin: Callable[[BenchConfig], Any] | None = None,
         prog: str = "botorl bench") -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--paper" in argv:
        # what a whole paper run costs, from the real pipeline's stages: its own options
        return paper_main(argv)
    paper = "" if twin else " (`botorl bench --paper --help`: what a whole paper run costs)"
    cfg = tyro.cli(BenchConfig, args=argv, prog=prog, description=__doc__.split("\n")[0] + paper)
    check_ranges(cfg)
    result = run(cfg, twin)
    print(format_table(result))
    if cfg.json:
        write_json(result, cfg.json)
        print(f"wrote {cfg.json}")
    return 0

"""``botorl bench --paper``: what a whole paper run costs, projected from short timed windows
of the real pipeline at the ``full`` profile. What it runs, how each stage's rate and compile
time are read from the run's ``metrics/*.csv`` and how a paper run is projected from them:
docs/performance.md, "What a paper run costs".

Peak host memory is each process's maximum resident size (``wait4``); peak device memory, off
the CPU, what the device's allocator reports at the process's end (``memory_stats``). Tasks
whose data cannot be made here (kitchen, pen) run on synthetic rows in the format each task
reads (a Minari dataset for kitchen, a Cal-QL expert ``.npy`` for pen), marked ``"data":
"synthetic"``: their rates are the real networks' and envs', their learning means nothing.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import jax
import numpy as np

from botorl.agents import population
from botorl.configs.members import Streams
from botorl.configs.presets import make_preset
from botorl.configs.resolve import resolve
from botorl.data.dataset import Dataset
from botorl.data.minari_io import write_minari
from botorl.envs.registry import get_task
from botorl.errors import ConfigError
from botorl.io import atomic_write_bytes
from botorl.jaxsetup import check_precision, matmul_precision, setup_jax
from botorl.pipeline.evaluation import make_eval_envs, run_episodes
from botorl.pipeline.policy import load_agent, read_run
from botorl.pipeline.rundir import CsvLog

# the paper's tasks as they can be run here: task -> where its data comes from
PAPER_TASKS = {
    "antmaze-large-diverse-local": "generated",
    "antmaze-large-play-local": "generated",
    "door-binary-local": "generated",
    "kitchen-partial-v0": "synthetic",
    "kitchen-mixed-v0": "synthetic",
    "pen-binary-v0": "synthetic",
}
# the paper's Table 3 (wall-clock per run, one RTX 3090), hours, by the task each stands for
PAPER_TABLE3_HOURS = {
    "antmaze-large-diverse": 2 + 48 / 60, "antmaze-large-play": 2 + 40 / 60, "kitchen-partial": 5 + 53 / 60,
    "kitchen-mixed": 4 + 51 / 60, "door-binary": 5 + 49 / 60, "pen-binary": 4 + 45 / 60,
}
STAGES = ("pretrain", "warmup", "boto", "finetune", "eval")


def paper_name(task: str) -> str:
    return task.removesuffix("-local").removesuffix("-v0").removesuffix("-v2")


def _synthetic_data(spec, work: Path, rows: int) -> tuple[list[str], list[str]]:
    """Random rows of the task's shapes (episodes of its horizon) in the format the task reads, and
    the flags of ``botorl run`` and of ``botorl eval`` that read them: a Minari dataset (kitchen),
    or a Cal-QL expert ``.npy`` of per-trajectory dicts (adroit binary: a pickle botorl wrote
    itself, which `eval` reads back from the run's config only with ``--allow-pickle``)."""
    rng = np.random.default_rng(0)
    r = {"observations": rng.normal(size=(rows, spec.obs_dim)).astype(np.float32),
         "next_observations": rng.normal(size=(rows, spec.obs_dim)).astype(np.float32),
         "actions": rng.uniform(-1, 1, (rows, spec.action_dim)).astype(np.float32),
         "rewards": (rng.uniform(size=rows) < 0.05).astype(np.float32),
         "ends": (np.arange(rows) + 1) % spec.max_episode_steps == 0}
    kind = spec.dataset_source.kind
    if kind == "minari":
        ds = Dataset(r["observations"], r["actions"], r["rewards"], r["next_observations"],
                     np.zeros(rows, bool), episode_ends=r["ends"], metadata={"source": "synthetic"})
        folder = write_minari(ds, path=work / f"{spec.name}-synthetic-v0", overwrite=True)
        return ["--data.path", str(folder)], []
    if kind == "calql_npy":
        cuts = np.flatnonzero(r["ends"]) + 1
        trajs = []
        for s, e in zip(np.r_[0, cuts[:-1]], cuts):
            rew = r["rewards"][s:e] - 1.0  # Cal-QL's binary {-1, 0}
            rew[-1] = 0.0  # every trajectory ends in a success, so none is dropped
            trajs.append({"observations": r["observations"][s:e], "next_observations": r["next_observations"][s:e],
                          "actions": r["actions"][s:e], "rewards": rew, "terminals": rew == 0.0})
        path = work / f"{spec.name}-synthetic-expert.npy"
        np.save(path, np.array(trajs, dtype=object), allow_pickle=True)
        return ["--data.path", str(path)], ["--allow-pickle"]
    raise ValueError(f"{spec.name}: no synthetic writer for data of kind {kind!r}")


def _run(cmd: list[str], log: Path, what: str) -> tuple[float, float, dict]:
    """(wall seconds, peak resident MB, its stats JSON: peak device memory and a timed evaluation's
    figures) of one botorl process (``cmd``: its command line, or ``["--time-eval", ...]``);
    RuntimeError, naming ``what``, if it fails."""
    t0 = time.perf_counter()
    stats = log.with_suffix(".stats.json")
    with open(log, "w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "botorl.benchmarks.measured_cli", str(stats), *cmd],
                                stdout=out, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if code := os.waitstatus_to_exitcode(status):
        raise RuntimeError(f"{what} exited {code}; see {log}")
    return wall, usage.ru_maxrss / 1024, json.loads(stats.read_text())  # Linux: KiB


def device_memory() -> dict[str, float | None]:
    """Peak and limit of the first device's memory in MB (None on a CPU, whose arrays are host
    memory, counted in the resident size)."""
    st = {}
    with contextlib.suppress(Exception):  # a backend without memory statistics
        st = jax.devices()[0].memory_stats() or {}
    return {name: st[k] / 2**20 if k in st else None
            for name, k in (("device_peak_mb", "peak_bytes_in_use"), ("device_limit_mb", "bytes_limit"))}


def time_evaluation(out: Path, members: int, episodes: int) -> dict:
    """``episodes`` evaluation episodes of every member of the run in ``out`` (its last
    checkpoint) as the run evaluates: all members' envs in one lockstep, one policy call per env
    step for all (botorl.pipeline.runner's ``RunContext.evaluate``), under the run's precision."""
    setup_jax()
    dirs = [out] if members == 1 else _member_dirs(out)
    cfgs = [read_run(d)[1] for d in dirs]
    cfg = replace(cfgs[0], eval=replace(cfgs[0].eval, episodes=episodes))
    spec = get_task(cfg.task)
    agents = population.stack([load_agent(d) for d in dirs])
    envs = [make_eval_envs(spec, cfg.eval) for _ in dirs]
    calls = 0

    def policy(obs):
        nonlocal calls
        calls += 1
        return population.eval_actions(agents, obs)

    try:
        with matmul_precision(cfg.precision):
            t0 = time.perf_counter()  # the first call compiles
            np.asarray(population.eval_actions(agents, np.zeros((len(dirs), len(envs[0]), spec.obs_dim), np.float32)))
            compile_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            stats = run_episodes(policy, envs, episodes=episodes, success_mode=spec.success_mode,
                                 seeds=[Streams.of(c).eval_command for c in cfgs], max_steps=spec.max_episode_steps)
            seconds = time.perf_counter() - t0
    finally:
        for es in envs:
            for e in es:
                e.close()
    lengths = [st.length for st in stats]
    return {"seconds": seconds, "compile_s": compile_s, "env_steps": float(sum(lengths) * episodes),
            "episode_length": float(np.mean(lengths)), "episodes": episodes, "members": len(dirs),
            "envs_per_member": len(envs[0]), "policy_calls": calls, "precision": cfg.precision}


def _member_dirs(out: Path) -> list[Path]:
    return [d for d in sorted(out.iterdir()) if (d / "summary.json").exists()]


def _steady(rows: list[dict], step_key: str, rate_key: str | None, seconds_key: str | None = None,
            start: int = 0) -> tuple[float, float]:
    """(steady-state rate, compile seconds) from a stage's metrics rows: the rows after the
    first give the rate; the first row's excess time over that rate is the compilation. The
    first row covers its steps since the stage's ``start`` (fine-tuning's rows are on the online
    axis, which starts after the warm-up's steps)."""
    if len(rows) < 2:
        raise RuntimeError("a stage logged fewer than 2 rows: raise its window")
    steps = [float(r[step_key]) - start for r in rows]
    if seconds_key is not None:  # cumulative seconds (BOTO)
        secs = [float(r[seconds_key]) for r in rows]
        rate = (steps[-1] - steps[0]) / max(secs[-1] - secs[0], 1e-9)
        return rate, max(secs[0] - steps[0] / rate, 0.0)
    rates = [float(r[rate_key]) for r in rows]
    rate = float(np.median(rates[1:]))
    first_s = steps[0] / rates[0] if rates[0] > 0 else 0.0
    return rate, max(first_s - steps[0] / rate, 0.0)


def measure(task: str, members: int, work: Path, windows: dict, data_steps: int) -> dict:
    """One task at one population size: each stage's rate, compile time, memory, projection."""
    spec = get_task(task)
    cfg = resolve(make_preset(task, "full", "boto"))
    out = work / f"{task}-n{members}"
    shutil.rmtree(out, ignore_errors=True)
    data_args = (_synthetic_data(spec, work, data_steps)[0] if PAPER_TASKS.get(task) == "synthetic"
                 else ["--data.steps", str(data_steps)])
    p, w, b, f = (windows[k] for k in ("pretrain", "warmup", "boto", "finetune"))
    seeds = ["--seeds", f"0-{members - 1}"] if members > 1 else ["--seed", "0"]
    cmd = ["run", "--task", task, "--method", "boto", "--profile", "full", *seeds, "--out", str(out),
           "--no-progress", "--no-tensorboard", *data_args,
           "--offline.steps", str(p), "--offline.log-every", str(max(1, p // 4)),
           "--offline.updates-per-call", str(max(1, p // 4)),
           "--warmup.steps", str(w), "--boto.boto-steps", str(b), "--boto.steps-per-call", str(max(1, b // 4)),
           "--online.steps", str(w + f), "--online.log-every", str(max(1, f // 4)),
           "--eval.episodes", "1", "--eval.interval", str(10 * (w + f)),
           "--checkpoint-every", str(10 * (w + f + p + b)),
           *(["--precision", windows["precision"]] if windows.get("precision") else [])]
    wall, rss, run_stats = _run(cmd, work / f"{task}-n{members}.log", f"{task}: `botorl run`")
    member = out if members == 1 else _member_dirs(out)[0]
    summary = json.loads((member / "summary.json").read_text())
    run_cfg = json.loads((member / "config.json").read_text())
    stages: dict[str, dict] = {}
    for stage, rate_key, seconds_key, unit, start in (("pretrain", "steps_per_s", None, "updates/s", 0),
                                                      ("boto", None, "seconds", "updates/s", 0),
                                                      ("finetune", "env_steps_per_s", None, "env steps/s (UTD 4)", w)):
        rate, comp = _steady(CsvLog(member / "metrics" / f"{stage}.csv").rows(), "step", rate_key, seconds_key, start)
        stages[stage] = {"rate": rate, "unit": unit, "compile_s": comp}
    # evaluation: every member's last checkpoint, all members' envs in one lockstep (as the run)
    _, ers, ev = _run(["--time-eval", str(out), str(members), str(windows["eval_episodes"])],
                      work / f"{task}-n{members}-eval.log", f"{task}: the timed evaluation")
    eval_rate = ev["env_steps"] / max(ev["seconds"], 1e-9)
    stages["eval"] = {"rate": eval_rate, "compile_s": ev["compile_s"], "policy_calls": ev["policy_calls"],
                      "unit": f"env steps/s of all members ({members} x {ev['envs_per_member']} envs in lockstep, "
                              f"one policy call per step)"}
    # the warm-up stage also ran one evaluation episode per member at step 0: take it out
    warm_s = summary["stage_seconds"]["warmup"] - members * ev["episode_length"] / eval_rate
    stages["warmup"] = {"rate": w / max(warm_s, 1e-9), "unit": "env steps/s (frozen policy)", "compile_s": 0.0}

    budget = paper_budget(cfg, spec.max_episode_steps)
    peaks = [x for x in (run_stats.get("device_peak_mb"), ev.get("device_peak_mb")) if x is not None]
    return {
        "task": task, "paper_task": paper_name(task), "data": PAPER_TASKS.get(task, "as configured"),
        "members": members, "precision": run_cfg.get("precision"), "stages": stages, "budget": budget,
        **project(stages, budget, members),
        "peak_host_mb": max(rss, ers), "device_memory_mb": max(peaks) if peaks else None,
        "device_memory_limit_mb": run_stats.get("device_limit_mb"), "measure_wall_s": wall,
        "paper_table3_hours": PAPER_TABLE3_HOURS.get(paper_name(task)),
    }


def paper_budget(cfg, horizon: int) -> dict[str, int]:
    """A paper run's work per stage: updates (pre-training, BOTO) or env steps (warm-up,
    fine-tuning after the warm-up, and every evaluation's episodes at the full horizon)."""
    return {"pretrain": cfg.offline.steps, "warmup": cfg.warmup.steps, "boto": cfg.boto.boto_steps,
            "finetune": cfg.online.steps - cfg.warmup.steps,
            "eval": (1 + cfg.online.steps // cfg.eval.interval) * cfg.eval.episodes * horizon}


def project(stages: dict[str, dict], budget: dict[str, int], members: int = 1) -> dict:
    """Hours of the whole budget at the measured rates, each stage compiled once; the
    population's wall time (every member evaluates its budget; the evaluation's rate counts all
    members' env steps, stepped together)."""
    seconds = {s: budget[s] / stages[s]["rate"] + stages[s]["compile_s"] for s in STAGES}
    seconds["eval"] *= members
    total = sum(seconds.values())
    return {"projected_hours": total / 3600, "hours_per_run": total / 3600 / members,
            "share": {s: seconds[s] / total for s in STAGES}}


def table(results: list[dict]) -> str:
    head = (f"{'task':30s} {'N':>3s} {'pretrain':>10s} {'warm-up':>9s} {'BOTO':>9s} {'fine-tune':>10s} "
            f"{'eval':>9s} {'hours':>8s} {'paper':>6s}  largest share")
    lines = [head, f"{'':30s} {'':>3s} {'upd/s':>10s} {'env st/s':>9s} {'upd/s':>9s} {'env st/s':>10s} "
                   f"{'env st/s':>9s} {'proj.':>8s} {'T3 h':>6s}"]
    for r in results:
        st = r["stages"]
        big = max(r["share"], key=r["share"].get)
        paper = r["paper_table3_hours"]
        lines.append(
            f"{r['task']:30s} {r['members']:3d} {st['pretrain']['rate']:10.1f} {st['warmup']['rate']:9.0f} "
            f"{st['boto']['rate']:9.1f} {st['finetune']['rate']:10.2f} {st['eval']['rate']:9.0f} "
            f"{r['projected_hours']:8.1f} {'-' if paper is None else f'{paper:.1f}':>6s}  "
            f"{big} {100 * r['share'][big]:.0f}%" + ("  (synthetic data)" if r["data"] == "synthetic" else ""))
    return "\n".join(lines)


def machine() -> dict:
    """The machine: host, and the device JAX runs on (its name, platform, count, memory)."""
    out = {"platform": platform.platform(), "processor": platform.processor(), "cpus": os.cpu_count()}
    with contextlib.suppress(Exception):  # the machine description is best effort
        setup_jax()
        d = jax.devices()[0]
        out.update({"device": str(d), "device_kind": d.device_kind, "backend": jax.default_backend(),
                    "device_count": jax.device_count(), "jax": jax.__version__,
                    "device_memory_limit_mb": device_memory()["device_limit_mb"]})
    return out


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="botorl bench --paper", description=__doc__.split("\n\n")[0])
    p.add_argument("--paper", action="store_true", help="(this benchmark)")
    p.add_argument("--tasks", default=",".join(PAPER_TASKS), help="comma-separated tasks")
    p.add_argument("--members", default="1", help="population sizes, e.g. 1,4,16")
    p.add_argument("--json", type=Path, default=None, help="write the results to this JSON file")
    p.add_argument("--pretrain-steps", type=int, default=48)
    p.add_argument("--warmup-steps", type=int, default=500)
    p.add_argument("--boto-steps", type=int, default=200)
    p.add_argument("--finetune-steps", type=int, default=100)
    p.add_argument("--eval-episodes", type=int, default=20, help="episodes of the timed evaluation (the paper's 20)")
    p.add_argument("--data-steps", type=int, default=20_000, help="rows of the (generated or synthetic) data")
    p.add_argument("--precision", default=None, help="the runs' matmul precision: highest, tf32 or bf16 "
                                                     "(default: the full preset's, tf32)")
    p.add_argument("--work", type=Path, default=None, help="folder for the runs (default: a temporary one)")
    args = p.parse_args(argv)
    try:
        members = [int(m) for m in args.members.split(",")]
    except ValueError:
        raise ConfigError(f"--members {args.members!r}: give population sizes like 1,4,16.") from None
    if args.precision is not None:
        check_precision(args.precision)
    tasks = [t for t in args.tasks.split(",") if t]
    windows = {"pretrain": args.pretrain_steps, "warmup": args.warmup_steps, "boto": args.boto_steps,
               "finetune": args.finetune_steps, "eval_episodes": args.eval_episodes, "precision": args.precision}
    flags = {**{f"--{k.replace('_', '-')}": v for k, v in vars(args).items() if k.endswith(("_steps", "_episodes"))},
             **{"--members": m for m in members if m < 1}}
    for flag, v in flags.items():
        if v < 1 or (flag in ("--pretrain-steps", "--boto-steps", "--finetune-steps") and v < 8):
            raise ConfigError(f"botorl bench --paper: {flag} {v} is too small (>= 8 for the stage windows "
                              "of pre-training, BOTO and fine-tuning, each logs 4 rows; >= 1 otherwise).")
    for t in tasks:
        get_task(t)  # an unknown task fails here, before any run
    work = args.work or Path(tempfile.mkdtemp(prefix="botorl-paper-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    results = []
    for t in tasks:
        for n in members:
            print(f"botorl bench --paper: {t}, {n} member(s) ...", flush=True)
            results.append(measure(t, n, work, windows, args.data_steps))
            print(table(results[-1:]).splitlines()[-1], flush=True)
    print("\n" + table(results))
    doc = {"machine": machine(), "precision": sorted({r["precision"] for r in results if r.get("precision")}),
           "windows": windows, "how": __doc__.split("\n\n", 1)[1], "results": results}
    m = doc["machine"]
    print(f"device: {m.get('device_kind', '?')} ({m.get('backend', '?')}, jax {m.get('jax', '?')}); matmul precision "
          f"{', '.join(doc['precision']) or '?'}; peak device memory "
          + ", ".join(f"{r['task']} x {r['members']}: " + ("- (a CPU's arrays are host memory, "
                                                          f"{r['peak_host_mb']:.0f} MB)" if r["device_memory_mb"] is None
                                                          else f"{r['device_memory_mb']:.0f} MB") for r in results))
    if args.json is not None:
        atomic_write_bytes(args.json, json.dumps(doc, indent=2).encode())
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0


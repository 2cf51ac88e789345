"""``botorl run``, ``botorl resume DIR``, ``botorl eval DIR``.

    botorl run [--task T] [--method M] [--seed S] [--alpha A] [--profile quick|full|smoke]
               [--pretrain calql|cql|iql] [--out DIR] [--demos PATH] [--<dotted.path> VALUE ...]

``run`` first reads --task, --method, --profile and --pretrain to pick the preset
(botorl.configs.presets), then tyro parses every argument over it, so any field of the
config can be set as ``--<dotted.path> VALUE`` (``botorl run --help`` lists them all). Bare
``botorl run`` is BOTO on pointmaze-large with the quick profile; its data are made on first
use. ``--demos PATH`` is short for ``--data.demos PATH`` (door-binary-local; default
$BOTORL_DOOR_DEMOS).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from botorl.errors import ConfigError

_SHORTCUTS = {"--demos": "--data.demos", "--dataset": "--data.path"}


def _expand_shortcuts(argv: list[str]) -> list[str]:
    out = []
    for a in argv:
        key, eq, val = a.partition("=")
        if key in _SHORTCUTS:
            out.append(_SHORTCUTS[key] + (eq + val if eq else ""))
        else:
            out.append(a)
    return out


def _pre_parse(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--task", default="pointmaze-large")
    p.add_argument("--method", default="boto")
    p.add_argument("--profile", default="quick")
    p.add_argument("--pretrain", default=None)
    ns, _ = p.parse_known_args(argv)
    if ns.pretrain in ("None", "none"):
        ns.pretrain = None
    return ns


def build_config(argv: list[str]):
    """Preset + command line -> resolved, validated RunConfig (ConfigError on bad input)."""
    import tyro

    from botorl.configs.presets import make_preset
    from botorl.configs.resolve import resolve, validate
    from botorl.configs.schema import RunConfig
    from botorl.pipeline.methods import get_method

    argv = _expand_shortcuts(list(argv))
    pre = _pre_parse(argv)
    get_method(pre.method)  # clear errors before tyro's generic ones
    from botorl.pipeline.methods import resolve_pretrain

    resolve_pretrain(pre.method, pre.pretrain)
    from botorl.envs.registry import get_task

    get_task(pre.task)
    default = make_preset(pre.task, pre.profile, pre.method, pre.pretrain)
    cfg = tyro.cli(
        RunConfig,
        default=default,
        args=argv,
        prog="botorl run",
        description="Run one method on one task, offline to online (preset: "
        f"task={pre.task}, method={pre.method}, profile={pre.profile}).",
    )
    cfg = resolve(cfg)
    validate(cfg)
    return cfg


def _default_out(cfg) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{cfg.task}-{cfg.method}-s{cfg.seed}-{stamp}"


def run_main(argv: list[str]) -> int:
    from botorl.jaxsetup import setup_jax

    setup_jax()
    cfg = build_config(argv)
    from dataclasses import replace

    from botorl.configs.schema import to_dict
    from botorl.envs.registry import get_task
    from botorl.pipeline.rundir import RunDir, atomic_write_json
    from botorl.pipeline.runner import execute, format_summary, load_offline

    out = Path(cfg.out) if cfg.out else _default_out(cfg)
    if (out / "config.json").exists():
        raise ConfigError(
            f"--out {out} already holds a run (config.json). Continue it with `botorl resume {out}`, "
            f"or pick another --out."
        )
    cfg = replace(cfg, out=str(out))
    spec = get_task(cfg.task)
    d_raw = load_offline(cfg, spec)  # a missing dataset fails here, before the run directory exists
    run = RunDir(out)
    run.create()
    atomic_write_json(run.config, to_dict(cfg))
    print(f"botorl: {cfg.method} on {cfg.task} (profile {cfg.profile}, seed {cfg.seed}) -> {out}", file=sys.stderr)
    summary = execute(cfg, run, d_raw, resume=False)
    print(format_summary(summary))
    return 0


def _load_run_config(directory: str):
    from botorl.configs.resolve import validate
    from botorl.configs.schema import RunConfig, from_dict
    from botorl.pipeline.rundir import RunDir, read_json

    run = RunDir(directory)
    if not run.config.exists():
        raise ConfigError(
            f"{directory} is not a botorl run directory (no config.json). Give the --out folder of a "
            f"`botorl run`."
        )
    try:
        cfg = from_dict(RunConfig, read_json(run.config))
    except (TypeError, ValueError, KeyError) as err:
        raise ConfigError(f"{run.config} cannot be read as a run config ({err}); was it edited by hand?") from None
    validate(cfg)
    return run, cfg


def resume_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="botorl resume", description="Continue a run directory from its last checkpoint.")
    p.add_argument("dir", help="the run directory (the --out of `botorl run`)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    args = p.parse_args(argv)
    from botorl.jaxsetup import setup_jax

    setup_jax()
    from dataclasses import replace

    from botorl.envs.registry import get_task
    from botorl.pipeline.rundir import read_json
    from botorl.pipeline.runner import execute, format_summary, load_offline

    run, cfg = _load_run_config(args.dir)
    if args.no_progress:
        cfg = replace(cfg, progress=False)
    if run.summary.exists():
        s = read_json(run.summary)
        if s.get("status") == "finished":
            print(f"botorl: {run.root} has finished already; nothing to resume.", file=sys.stderr)
            print(format_summary(s))
            return 0
    spec = get_task(cfg.task)
    d_raw = load_offline(cfg, spec)
    summary = execute(cfg, run, d_raw, resume=True)
    print(format_summary(summary))
    return 0


def eval_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="botorl eval", description="Evaluate the last checkpoint of a run directory.")
    p.add_argument("dir", help="the run directory")
    p.add_argument("--episodes", type=int, default=None, help="episodes (default: the run's eval.episodes)")
    p.add_argument("--checkpoint", default=None, help="checkpoint folder name (default: the latest)")
    args = p.parse_args(argv)
    from botorl.jaxsetup import setup_jax

    setup_jax()
    from dataclasses import replace

    from botorl.envs.registry import get_task
    from botorl.pipeline import stages as S
    from botorl.pipeline.checkpoint import CheckpointManager
    from botorl.pipeline.evaluation import QProbe, run_episodes
    from botorl.pipeline.rundir import atomic_write_json
    from botorl.pipeline.runner import load_offline, transform_dataset

    run, cfg = _load_run_config(args.dir)
    if args.episodes is not None:
        if args.episodes < 1:
            raise ConfigError(f"--episodes {args.episodes}: give at least 1 episode.")
        cfg = replace(cfg, eval=replace(cfg.eval, episodes=args.episodes))
    ckpt = CheckpointManager(run.checkpoints)
    if args.checkpoint:
        if not ckpt.exists(args.checkpoint):
            names = sorted(q.name for q in run.checkpoints.iterdir() if q.is_dir() and not q.name.startswith("."))
            raise ConfigError(f"--checkpoint {args.checkpoint} is not in {run.checkpoints}; there are: {', '.join(names) or 'none'}.")
        name = args.checkpoint
    else:
        latest = ckpt.latest()
        if latest is None:
            raise ConfigError(f"{run.root} has no checkpoint yet; wait for the first stage to finish.")
        name = latest["name"]
    state = ckpt.state(name)
    spec = get_task(cfg.task)
    d = transform_dataset(cfg, spec, load_offline(cfg, spec))
    stage = state["stage"]
    template = (S.make_online_agent_template if stage == "finetune" else S.make_pretrain_agent)(
        cfg, d.obs_dim, d.action_dim, cfg.seed)
    from botorl.agents import checkpoint as agent_ckpt

    agent = agent_ckpt.load(ckpt.path(name) / "agent.ckpt", like=template)
    n = min(cfg.eval.num_envs, cfg.eval.episodes)
    envs = [spec.make_env(seed=10_000 + i, evaluation=True) for i in range(n)]
    t0 = time.perf_counter()
    stats = run_episodes(lambda o: agent.eval_actions(o), envs, episodes=cfg.eval.episodes,
                         success_mode=spec.success_mode, seed=200_000 + cfg.seed, max_steps=spec.max_episode_steps)
    q_data, q_uniform = QProbe(d.observations, d.actions, seed=12345, size=cfg.eval.q_pairs)(S.q_fn(agent))
    for e in envs:
        e.close()
    result = {"checkpoint": name, "stage": stage, "step": state.get("step"), "episodes": cfg.eval.episodes,
              "success": stats.success, "return": stats.episode_return, "episode_length": stats.length,
              "q_data": q_data, "q_uniform": q_uniform, "seconds": round(time.perf_counter() - t0, 2)}
    atomic_write_json(run.root / f"eval-{name}.json", result)
    for k, v in result.items():
        print(f"{k:<15} {v:.4g}" if isinstance(v, float) else f"{k:<15} {v}")
    return 0

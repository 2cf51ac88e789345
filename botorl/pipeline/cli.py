"""``botorl run``, ``botorl resume DIR``, ``botorl eval DIR``.

    botorl run [--task T] [--method M] [--seed S] [--alpha A] [--profile quick|full|smoke]
               [--pretrain calql|cql|iql] [--out DIR] [--demos PATH] [--<dotted.path> VALUE ...]

``run`` first reads --task, --method, --profile and --pretrain to pick the preset
(botorl.configs.presets), then tyro parses every argument over it, so any field of the
config can be set as ``--<dotted.path> VALUE`` (``botorl run --help`` lists them all). Bare
``botorl run`` is BOTO on pointmaze-umaze with the quick profile; its data are made on first
use. ``--demos PATH`` is short for ``--data.demos PATH`` (door-binary-local; default
$BOTORL_DOOR_DEMOS, else the copy shipped in botorl/data/assets).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from botorl.configs.build import build_config
from botorl.errors import BotorlError, ConfigError
from botorl.pipeline import preempt
from botorl.pipeline.rundir import check_out, io_fault, owned


def _mark_failed(run, reason: str, cfg=None) -> None:
    """summary.json says ``failed`` with the reason, when it can still be written."""
    from botorl.io import atomic_write_json
    from botorl.pipeline.rundir import read_json

    try:
        summary = read_json(run.summary) if run.summary.exists() else None
    except (OSError, ValueError):
        summary = None
    if not isinstance(summary, dict):
        summary = {}
        if cfg is not None:  # no usable summary yet: one with every contract key
            try:
                from botorl.pipeline.runner import build_summary

                summary = build_summary(cfg, run, "failed", {}, reason)
            except Exception:
                summary = {}
    summary.update(status="failed", error=reason)
    try:
        atomic_write_json(run.summary, summary)
    except OSError:
        # A full disk has no room for the temp file of an atomic write; rewriting the old
        # summary in place reuses its blocks. Not atomic, so only as the fallback.
        try:
            import json
            import os

            from botorl.io import open_regular

            text = json.dumps(summary, indent=2, default=str) + "\n"
            with os.fdopen(open_regular(run.summary, os.O_RDWR | os.O_CREAT), "r+") as f:  # never through a link
                f.seek(0)
                f.truncate()
                f.write(text)
        except (OSError, BotorlError):
            pass  # read-only, gone or not a regular file: the exit code and the message still say it


def _execute_guarded(cfg, run, d_raw, *, resume: bool, resume_from: str | None = None):
    """``execute`` with I/O faults and corrupt checkpoints turned into exit 2 and a truthful status."""
    from botorl.pipeline.checkpoint import CheckpointCorrupt, CheckpointManager
    from botorl.pipeline.runner import execute

    try:
        if resume_from is not None:
            # latest.json is pointed at the chosen (verified) checkpoint; execute(resume=True)
            # starts from ckpt.latest(), so the runner needs no argument for it.
            CheckpointManager(run.checkpoints).select(resume_from)
        return execute(cfg, run, d_raw, resume=resume)
    except OSError as err:
        fault = io_fault(err, run.root)
        if fault is None:
            raise
        _mark_failed(run, str(fault), cfg)
        raise fault from None
    except CheckpointCorrupt as err:
        msg = f"{err} {_resume_hint(run, resume_from)}" if resume else str(err)
        _mark_failed(run, msg, cfg)
        raise BotorlError(msg) from None
    except BotorlError as err:
        _mark_failed(run, str(err), cfg)
        raise
    except (ValueError, KeyError) as err:
        if not resume:
            raise
        # a damaged latest.json / state.json / buffer.npz read during the resume
        msg = (f"{run.root}: a checkpoint file could not be read on resume ({type(err).__name__}: {err}). "
               f"{_resume_hint(run, resume_from)}")
        _mark_failed(run, msg, cfg)
        raise BotorlError(msg) from None


def _resume_hint(run, resume_from: str | None) -> str:
    """The command that resumes from the newest checkpoint that passes the check, other than
    the one that just failed (a hint that names a command that works)."""
    from botorl.pipeline.checkpoint import CheckpointManager

    ckpt = CheckpointManager(run.checkpoints)
    failed = resume_from or (ckpt.latest() or {}).get("name")
    good = [n for n in sorted(ckpt.names(), key=ckpt.order, reverse=True) if n != failed and ckpt.usable(n)]
    if not good:
        return "No other checkpoint passes the check; start the run again with `botorl run` and another --out."
    others = f" (others that pass: {', '.join(good[1:])})" if good[1:] else ""
    return f"Resume from an earlier checkpoint: `botorl resume {run.root} --from {good[0]}`{others}."


def _default_out(cfg) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{cfg.task}-{cfg.method}-s{cfg.seed}-{stamp}"


def run_main(argv: list[str]) -> int:
    from botorl.configs.members import is_population
    from botorl.jaxsetup import setup_jax

    setup_jax()
    cfg = build_config(argv)
    if cfg.wandb:  # before any work: a missing wandb must not leave a run directory behind
        from botorl.pipeline.tracking import require_wandb

        require_wandb()
    if is_population(cfg):  # --seeds / --alphas: a population (botorl/pipeline/population_cli.py)
        from botorl.pipeline.population_cli import run_population_main

        return run_population_main(cfg)
    from dataclasses import replace

    from botorl.configs.schema import to_dict
    from botorl.envs.registry import get_task
    from botorl.io import atomic_write_json
    from botorl.pipeline.rundir import RunDir
    from botorl.pipeline.runner import format_summary, load_offline

    out = Path(cfg.out) if cfg.out else _default_out(cfg)
    check_out(out)

    def already_a_run():
        if (out / "config.json").exists():
            raise ConfigError(
                f"--out {out} already holds a run (config.json). Continue it with `botorl resume {out}`, "
                f"or pick another --out."
            )

    already_a_run()
    cfg = replace(cfg, out=str(out))
    spec = get_task(cfg.task)
    d_raw = load_offline(cfg, spec)  # a missing dataset fails here, before the run directory exists
    if cfg.pretrained is not None:  # so does a --pretrained without this seed's pre-training
        from botorl.pipeline import shared_pretrain

        shared_pretrain.match([cfg], cfg.pretrained)
    run = RunDir(out)
    with owned(out):
        already_a_run()  # again, under the lock: another `run` may have started meanwhile
        try:
            run.create()
            atomic_write_json(run.config, to_dict(cfg))
        except OSError as err:
            fault = io_fault(err, out)
            if fault is None:
                raise
            raise fault from None
        print(f"botorl: {cfg.method} on {cfg.task} (profile {cfg.profile}, seed {cfg.seed}) -> {out}", file=sys.stderr)
        with preempt.resumable(f"botorl resume {out}"):
            summary = _execute_guarded(cfg, run, d_raw, resume=False)
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
        data = read_json(run.config)
        if not isinstance(data, dict):
            raise ValueError("not a JSON object")
        cfg = from_dict(RunConfig, data)
    except (OSError, TypeError, ValueError, KeyError, AttributeError) as err:
        raise ConfigError(f"{run.config} cannot be read as a run config ({err}); was it edited by hand?") from None
    validate(cfg)
    return run, cfg


ALLOW_PICKLE_HELP = ("open a pickle-based dataset (Cal-QL .npy, DAPG .pickle) named in the run's config.json; "
                     "without it botorl refuses, as a pickle from a run directory could run code")

# resume and eval parse with tyro as run, sweep and report do: one help style for every command
_Dir = Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="DIR")]
_Flag = tyro.conf.FlagCreatePairsOff[bool]  # --no-progress alone, not --no-progress / --no-no-progress


@dataclass
class ResumeArgs:
    """Continue a run (or population) directory from its last checkpoint; a run stopped by
    SIGTERM / SIGINT continues from the checkpoint it wrote then."""

    dir: _Dir
    """the run directory (the --out of `botorl run`)"""
    from_: Annotated[str | None, tyro.conf.arg(name="from", metavar="NAME",
                                               help_behavior_hint="(default: the newest verified one)")] = None
    """resume from this checkpoint folder of DIR/checkpoints"""
    no_progress: _Flag = False
    """no progress bars"""
    allow_pickle: Annotated[_Flag, tyro.conf.arg(help=ALLOW_PICKLE_HELP)] = False


@dataclass
class EvalArgs:
    """Evaluate the last checkpoint of a run directory (or the one --checkpoint names)."""

    dir: _Dir
    """the run directory"""
    episodes: Annotated[int | None, tyro.conf.arg(metavar="N", help_behavior_hint="(default: the run's eval.episodes)")] = None
    """evaluation episodes"""
    checkpoint: Annotated[str | None, tyro.conf.arg(metavar="NAME", help_behavior_hint="(default: the latest)")] = None
    """checkpoint folder name in DIR/checkpoints"""
    policy: Annotated[str | None, tyro.conf.arg(metavar="FILE.onnx")] = None
    """evaluate this exported model (`botorl export`) through onnxruntime instead of a checkpoint, on the same
    episodes (needs pip install "botorl[export]")"""
    allow_pickle: Annotated[_Flag, tyro.conf.arg(help=ALLOW_PICKLE_HELP)] = False


def resume_main(argv: list[str]) -> int:
    args = tyro.cli(ResumeArgs, args=argv, prog="botorl resume")
    if (Path(args.dir) / "population.json").exists():  # a population (botorl/pipeline/population_cli.py)
        from botorl.pipeline.population_cli import resume_population_main

        return resume_population_main(args.dir, no_progress=args.no_progress, allow_pickle=args.allow_pickle)
    from botorl.jaxsetup import setup_jax

    setup_jax()
    from dataclasses import replace

    from botorl.envs.registry import get_task
    from botorl.pipeline.checkpoint import CheckpointManager
    from botorl.pipeline.rundir import read_json
    from botorl.pipeline.runner import format_summary

    run, cfg = _load_run_config(args.dir)
    if cfg.wandb:
        from botorl.pipeline.tracking import require_wandb

        require_wandb()
    with owned(run.root):
        if args.no_progress:
            cfg = replace(cfg, progress=False)
        if args.from_ is not None:
            CheckpointManager(run.checkpoints).verify_named(args.from_)  # exit 2 naming the choices
            print(f"botorl: resuming from the chosen checkpoint {args.from_}", file=sys.stderr)
        elif run.summary.exists():
            try:
                s = read_json(run.summary)
            except (OSError, ValueError):
                s = {}  # a damaged summary is rewritten by the resume
            if isinstance(s, dict) and s.get("status") == "finished":
                print(f"botorl: {run.root} has finished already; nothing to resume.", file=sys.stderr)
                try:
                    print(format_summary(s))
                except (KeyError, TypeError, ValueError, AttributeError):  # a summary edited by hand
                    print(f"status finished (the rest of {run.summary} cannot be shown)")
                return 0
        spec = get_task(cfg.task)
        d_raw = _load_run_data(cfg, spec, run, args.allow_pickle)
        with preempt.resumable(f"botorl resume {run.root}"):
            summary = _execute_guarded(cfg, run, d_raw, resume=True, resume_from=args.from_)
    print(format_summary(summary))
    return 0


def _load_run_data(cfg, spec, run, allow_pickle: bool):
    """The offline data of a run read back from its config.json: no pickle unless allowed."""
    from botorl.data.loaders import refuse_pickle
    from botorl.pipeline.runner import load_offline

    if allow_pickle:
        return load_offline(cfg, spec)
    with refuse_pickle(f"the run directory's {run.config}"):
        return load_offline(cfg, spec)


def eval_main(argv: list[str]) -> int:
    args = tyro.cli(EvalArgs, args=argv, prog="botorl eval")
    from botorl.jaxsetup import setup_jax

    setup_jax()
    run, cfg = _load_run_config(args.dir)
    if args.policy is not None:  # an exported model through onnxruntime (botorl/pipeline/export.py)
        if args.checkpoint is not None:
            raise ConfigError("--policy and --checkpoint: the model names its checkpoint (in FILE.onnx.json); give one.")
        if args.episodes is not None and args.episodes < 1:
            raise ConfigError(f"--episodes {args.episodes}: give at least 1 episode.")
        from botorl.pipeline.export import evaluate_exported

        with owned(run.root):
            result = evaluate_exported(run, cfg, args.policy, episodes=args.episodes)
        for k, v in result.items():
            print(f"{k:<15} {v:.4g}" if isinstance(v, float) else f"{k:<15} {v}")
        return 0
    with owned(run.root):
        try:
            return _eval(args, run, cfg)
        except OSError as err:
            fault = io_fault(err, run.root)
            if fault is None:
                raise
            raise fault from None


def _eval(args, run, cfg) -> int:
    from dataclasses import replace

    from botorl.agents import checkpoint as agent_ckpt
    from botorl.envs.registry import get_task
    from botorl.pipeline import stages as S
    from botorl.configs.schema import run_identity
    from botorl.pipeline.checkpoint import CheckpointManager, check_identity
    from botorl.pipeline.evaluation import QProbe, make_eval_envs, run_episodes
    from botorl.io import atomic_write_json
    from botorl.pipeline.runner import transform_dataset

    if args.episodes is not None:
        if args.episodes < 1:
            raise ConfigError(f"--episodes {args.episodes}: give at least 1 episode.")
        cfg = replace(cfg, eval=replace(cfg.eval, episodes=args.episodes))
    ckpt = CheckpointManager(run.checkpoints)
    if args.checkpoint:
        ckpt.verify_named(args.checkpoint)
        name = args.checkpoint
    else:
        latest = ckpt.latest()
        if latest is None:
            raise ConfigError(f"{run.root} has no checkpoint yet; wait for the first stage to finish.")
        name = latest["name"]
    state = ckpt.state(name)
    check_identity(state, [run_identity(cfg)], run.checkpoints, name)
    spec = get_task(cfg.task)
    d = transform_dataset(cfg, spec, _load_run_data(cfg, spec, run, args.allow_pickle))
    stage = state["stage"]
    template = (S.make_online_agent_template if stage == "finetune" else S.make_pretrain_agent)(
        cfg, d.obs_dim, d.action_dim, cfg.seed)
    agent = agent_ckpt.load(ckpt.file(name, "agent.ckpt"), like=template)
    envs = make_eval_envs(spec, cfg.eval)
    t0 = time.perf_counter()
    stats = run_episodes(lambda o: agent.eval_actions(o[0])[None], [envs], episodes=cfg.eval.episodes,
                         success_mode=spec.success_mode, seeds=[200_000 + cfg.seed], max_steps=spec.max_episode_steps)[0]
    q_data, q_uniform = QProbe(d.observations, d.actions, seed=12345, size=cfg.eval.q_pairs)(S.q_fn(agent))
    for e in envs:
        e.close()
    step = state.get("step")
    if step is None and state.get("stage_done"):  # a stage's final checkpoint: the stage's whole budget
        step = {"pretrain": cfg.offline.steps, "warmup": cfg.warmup.steps, "boto": cfg.boto.boto_steps,
                "finetune": cfg.online.steps}.get(stage)
    result = {"checkpoint": name, "stage": stage, "step": step, "episodes": cfg.eval.episodes,
              "success": stats.success, "return": stats.episode_return, "episode_length": stats.length,
              "q_data": q_data, "q_uniform": q_uniform, "seconds": round(time.perf_counter() - t0, 2)}
    atomic_write_json(run.root / f"eval-{name}.json", result)
    for k, v in result.items():
        print(f"{k:<15} {v:.4g}" if isinstance(v, float) else f"{k:<15} {v}")
    return 0

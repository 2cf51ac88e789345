"""``botorl run``, ``botorl resume DIR``, ``botorl eval DIR``, ``botorl export RUN_DIR``
(docs/running.md; a population's directory: docs/populations.md).

Imported only when one of these commands runs (botorl/cli.py), so its JAX and gymnasium
imports (the runner, the stages, the configs' schema) are at module level; `botorl --help` and
`import botorl` stay without them.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated, Literal

import tyro

from botorl.agents import agent_file
from botorl.configs.build import build_config
from botorl.configs.custom import register_given
from botorl.configs.members import MEMBER_NAME, Streams, is_population, member_config, population
from botorl.configs.resolve import BOUNDS, check_bounds, validate
from botorl.configs.schema import RunConfig, from_dict, to_dict
from botorl.envs.registry import get_task
from botorl.errors import BotorlError, ConfigError, Range, check_ranges, warn
from botorl.io import atomic_write_json, open_regular, own_folder, read_json_object
from botorl.jaxsetup import matmul_precision, setup_jax
from botorl.pipeline import preempt, shared_pretrain, stages
from botorl.pipeline.checkpoint import CheckpointCorrupt, CheckpointManager, check_identity, checkpoint_step, \
    full_identity
from botorl.pipeline.evaluation import QProbe, evaluate_command
from botorl.pipeline.export import contract_path, evaluate_exported, export_policy
from botorl.pipeline.memory import check_fits
from botorl.pipeline.policy import check_checkpoint, read_run
from botorl.pipeline.provenance import environment_record
from botorl.pipeline.rundir import POPULATION_FILE, RunDir, RunLock, check_out, io_guard, read_json
from botorl.pipeline.runner import execute, load_offline, load_run_data, transform_dataset
from botorl.pipeline.summary import build_summary, format_population, format_summary, read_summary, \
    write_population_file
from botorl.pipeline.tracking import require_wandb


def _mark_failed(path: Path, reason: str, fresh=None) -> None:
    """``path`` (a summary.json or population.json) says ``failed`` with the reason, when it can
    still be written; where none can be read, ``fresh()``'s (a summary with every contract key)."""
    data = read_json_object(path)
    if data is None:
        if fresh is None:
            return
        try:
            data = fresh()
        except Exception:
            data = {}
    data.update(status="failed", error=reason)
    try:
        atomic_write_json(path, data)
    except OSError:
        # A full disk has no room for the temp file of an atomic write; rewriting the old
        # file in place reuses its blocks. Not atomic, so only as the fallback.
        # (read-only, gone or not a regular file: the exit code and the message still say it)
        with contextlib.suppress(OSError, BotorlError):
            with os.fdopen(open_regular(path, os.O_RDWR | os.O_CREAT), "r+") as f:  # never through a link
                f.truncate()
                f.write(json.dumps(data, indent=2, default=str) + "\n")


def _execute(cfg, member_cfgs, root: Path, runs: list[RunDir], d_raw, *, resume: bool, resume_from: str | None = None):
    """``runner.execute`` with I/O faults and corrupt checkpoints turned into exit 2 and a truthful
    status (the run's summary.json, a population's population.json), an interrupt into ``botorl resume ROOT``."""
    def mark(reason: str) -> None:
        if runs[0].root == root:  # a single run
            _mark_failed(runs[0].summary, reason, lambda: build_summary(cfg, runs[0], "failed", {}, reason))
        else:
            _mark_failed(root / POPULATION_FILE, reason)

    try:
        with preempt.resumable(f"botorl resume {root}"), io_guard(root):
            if resume_from is not None:
                # latest.json is pointed at the chosen (verified) checkpoint; execute(resume=True)
                # starts from ckpt.latest(), so the runner needs no argument for it.
                CheckpointManager(RunDir(root).checkpoints).select(resume_from)
            return execute(cfg, member_cfgs, root, runs, d_raw, resume=resume)
    except (CheckpointCorrupt, ValueError, KeyError) as err:
        corrupt = isinstance(err, CheckpointCorrupt)
        if not (corrupt or resume):
            raise
        # else a damaged latest.json / state.json / buffer.npz read during the resume
        msg = str(err) if corrupt else f"{root}: a checkpoint file could not be read on resume ({type(err).__name__}: {err})."
        msg = f"{msg} {_resume_hint(root, resume_from)}" if resume else msg
        mark(msg)
        raise BotorlError(msg) from None
    except BotorlError as err:
        mark(str(err))
        raise


def _resume_hint(root: Path, resume_from: str | None) -> str:
    """The command that resumes from the newest checkpoint that passes the check, other than
    the one that just failed (a hint that names a command that works)."""
    ckpt = CheckpointManager(RunDir(root).checkpoints)
    failed = resume_from or (ckpt.latest() or {}).get("name")
    good = [n for n in sorted(ckpt.names(), key=ckpt.order, reverse=True) if n != failed and ckpt.usable(n)]
    if not good:
        return "No other checkpoint passes the check; start the run again with `botorl run` and another --out."
    others = f" (others that pass: {', '.join(good[1:])})" if good[1:] else ""
    return f"Resume from an earlier checkpoint: `botorl resume {root} --from {good[0]}`{others}."


def _print_summaries(summaries: list[dict], single: bool) -> None:
    print(format_summary(summaries[0]) if single else format_population(summaries))


def run_main(argv: list[str]) -> int:
    setup_jax()
    print_config = "--print-config" in argv
    cfg = build_config([a for a in argv if a != "--print-config"])
    if print_config:  # the resolved config, as config.json would hold it; nothing is written
        print(json.dumps(to_dict(cfg), indent=2, sort_keys=True))
        return 0
    if cfg.wandb:  # before any work: a missing wandb must not leave a run directory behind
        require_wandb()
    single = not is_population(cfg)  # --seeds / --alphas: a population
    members, member_cfgs = (None, [cfg]) if single else population(cfg)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    name = f"s{cfg.seed}" if single else f"pop{len(members)}"
    out = Path(cfg.out) if cfg.out else Path("runs") / f"{cfg.task}-{cfg.method}-{name}-{stamp}"
    check_out(out)

    def already():
        for f in ("config.json", POPULATION_FILE):
            if (out / f).exists():
                raise ConfigError(f"--out {out} already holds a run or population ({f}). Continue it with "
                                  f"`botorl resume {out}`, or pick another --out.")

    already()
    cfg = replace(cfg, out=str(out))
    spec = get_task(cfg.task)
    d_raw = load_offline(cfg, spec)  # a missing dataset fails here, before any directory exists
    if cfg.pretrained is not None:  # so does a --pretrained without every member's pre-training
        shared_pretrain.match(member_cfgs, cfg.pretrained)
    if not single:
        check_fits(cfg, len(members), d_raw, spec)
    runs = [RunDir(out)] if single else [RunDir(out / m.name) for m in members]
    member_cfgs = [replace(c, out=str(r.root)) for c, r in zip(member_cfgs, runs)]
    with RunLock(out):
        already()  # again, under the lock: another `run` may have started meanwhile
        with io_guard(out):
            environment = environment_record()  # what the run was made with (pipeline/provenance.py)
            for c, r in zip(member_cfgs, runs):
                own_folder(out, r.root)  # a member's folder planted as a link would take its run outside --out
                r.create()
                atomic_write_json(r.config, {**to_dict(c), "environment": environment}, root=out)
            if not single:
                write_population_file(out, cfg, member_cfgs, "running", ["running"] * len(members), {})
        what = (f"(profile {cfg.profile}, seed {cfg.seed})" if single else
                f"(profile {cfg.profile}), a population of {len(members)}: {', '.join(m.name for m in members)}")
        print(f"botorl: {cfg.method} on {cfg.task} {what} -> {out}", file=sys.stderr)
        summaries = _execute(cfg, member_cfgs, out, runs, d_raw, resume=False)
    _print_summaries(summaries, single)
    return 0


def member_dir(root: Path, entry) -> Path:
    """The run directory of a population member named in population.json: only a name botorl
    itself makes (``seed<k>``, ``alpha<+0.50>-seed<k>``: configs.members.Member.name) of a
    real folder directly inside ``root``; ConfigError (exit 2) for anything else."""
    name = entry.get("name") if isinstance(entry, dict) else None
    if not isinstance(name, str) or not MEMBER_NAME.fullmatch(name):
        raise ConfigError(f"{root / POPULATION_FILE} names a member {name!r}, which is not a member name botorl "
                          f"makes (seed<k> or alpha<+a.aa>-seed<k>); the file was edited or is not botorl's.")
    path = root / name
    if path.is_symlink() or (path.exists() and path.resolve().parent != root.resolve()):
        raise ConfigError(f"{path} is a link out of the population directory {root}; a member's run directory must "
                          f"be a folder inside it.")
    return path


def load_population(directory: str | Path, entry: str | None = None, checkpoint: str | None = None):
    """(shared config, member configs, member run dirs, population.json) of a population directory;
    ``entry``: the user's ``--env`` for a task of one's own (configs/custom.py); the checkpoint a
    resume starts from (``checkpoint``, else the latest) is checked to be the population's before
    any task is registered."""
    root = Path(directory)
    try:
        data = read_json(root / POPULATION_FILE)
        cfg = from_dict(RunConfig, data["config"])
        if not isinstance(data["members"], list) or not data["members"]:
            raise ValueError("no member list")
        runs = [RunDir(member_dir(root, m)) for m in data["members"]]
        member_cfgs = [from_dict(RunConfig, read_json(r.config)) for r in runs]
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
        raise ConfigError(f"{root / POPULATION_FILE} (or a member's config.json) cannot be read ({err}); "
                          f"was it edited by hand?") from None
    if len({r.root.name for r in runs}) != len(runs):
        raise ConfigError(f"{root / POPULATION_FILE} names a member twice; was it edited by hand?")
    for c in [cfg, *member_cfgs]:
        check_bounds(c)
    check_resume_point(root, member_cfgs, checkpoint)
    register_given(cfg, entry)
    validate(cfg)
    for r, member_cfg in zip(runs, member_cfgs):
        # a member differs from the population in its seed, alpha and folder only
        want = member_config(cfg, member_cfg.seed, member_cfg.alpha, member_cfg.out)
        if replace(member_cfg, progress=cfg.progress) != want:
            raise ConfigError(f"{r.config} does not describe a member of the population in {root} (its settings "
                              f"other than seed and alpha differ from {root / POPULATION_FILE}'s config); was it "
                              f"edited by hand?")
    # where the members are is where they were found, whatever the files say
    member_cfgs = [replace(c, out=str(r.root)) for r, c in zip(runs, member_cfgs)]
    return replace(cfg, out=str(root)), member_cfgs, runs, data


def check_resume_point(root: Path, cfgs, checkpoint: str | None = None) -> None:
    """The checkpoint a resume of ``root`` starts from (``checkpoint``, else the latest that passes
    its check; none yet: nothing to check) must be the run's own (``check_identity``): checked
    before a task is registered or data read. A damaged one is left to the resume, which names it
    and falls back."""
    ckpt = CheckpointManager(RunDir(root).checkpoints)
    with contextlib.suppress(CheckpointCorrupt):
        name = ckpt.chosen(checkpoint) if checkpoint is not None else (ckpt.latest() or {}).get("name")
        if name is not None:
            check_identity(ckpt.state(name), [full_identity(c) for c in cfgs], ckpt.root, name)


ENV_HELP = ("a task of your own: its entry point MODULE:FUNCTION again (the one the run recorded); botorl never "
            "imports what a run directory's files name")
ALLOW_PICKLE_HELP = ("open a pickle-based dataset (Cal-QL .npy, DAPG .pickle) named in the run's config.json; "
                     "without it botorl refuses, as a pickle from a run directory could run code")

# resume, eval and export parse with tyro as run, sweep and report do: one help style for every command
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
    env: Annotated[str | None, tyro.conf.arg(metavar="MODULE:FUNCTION", help=ENV_HELP)] = None


@dataclass
class EvalArgs:
    """Evaluate the last checkpoint of a run directory (or the one --checkpoint names)."""

    dir: _Dir
    """the run directory"""
    episodes: Annotated[int | None, tyro.conf.arg(metavar="N", help_behavior_hint="(default: the run's eval.episodes)"),
                        Range(1, BOUNDS["eval.episodes"])] = None
    """evaluation episodes"""
    checkpoint: Annotated[str | None, tyro.conf.arg(metavar="NAME", help_behavior_hint="(default: the latest)")] = None
    """checkpoint folder name in DIR/checkpoints"""
    policy: Annotated[str | None, tyro.conf.arg(metavar="FILE.onnx")] = None
    """evaluate this exported model (`botorl export`) through onnxruntime instead of a checkpoint, on the same
    episodes (needs pip install "botorl[export]")"""
    allow_pickle: Annotated[_Flag, tyro.conf.arg(help=ALLOW_PICKLE_HELP)] = False
    env: Annotated[str | None, tyro.conf.arg(metavar="MODULE:FUNCTION", help=ENV_HELP)] = None


@dataclass
class ExportArgs:
    """Export a run's policy to ONNX, with its contract (FILE.json), verified against
    `botorl.load_policy` with onnxruntime before it exits. Needs the export extra:
    pip install "botorl[export]"."""

    dir: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="RUN_DIR")]
    """the run directory (the --out of `botorl run`)"""
    checkpoint: Annotated[str | None, tyro.conf.arg(metavar="NAME", help_behavior_hint="(default: the latest)")] = None
    """checkpoint folder name in RUN_DIR/checkpoints"""
    format: Literal["onnx"] = "onnx"
    """the model format"""
    out: Annotated[str | None, tyro.conf.arg(metavar="FILE", help_behavior_hint="(default: RUN_DIR/policy.onnx)")] = None
    """the model file; its contract is FILE.json"""
    force: _Flag = False
    """overwrite FILE and FILE.json if they exist (regular files only)"""
    env: Annotated[str | None, tyro.conf.arg(metavar="MODULE:FUNCTION", help=ENV_HELP)] = None


def resume_main(argv: list[str]) -> int:
    args = tyro.cli(ResumeArgs, args=argv, prog="botorl resume")
    setup_jax()
    root = Path(args.dir)
    single = not (root / POPULATION_FILE).exists()
    if single:
        run, cfg = read_run(root, "resume", validate=True, entry=args.env,
                            before=lambda r, c: check_resume_point(r.root, [c], args.from_))
        member_cfgs, runs, status_file, origin = [cfg], [run], run.summary, run.config
    else:
        cfg, member_cfgs, runs, _ = load_population(root, args.env, args.from_)
        status_file = origin = root / POPULATION_FILE
    if cfg.wandb:
        require_wandb()
    with RunLock(root):
        if args.no_progress:
            cfg = replace(cfg, progress=False)
            member_cfgs = [replace(c, progress=False) for c in member_cfgs]
        if args.from_ is not None:
            CheckpointManager(RunDir(root).checkpoints).verify_named(args.from_)  # exit 2 naming the choices
            print(f"botorl: resuming from the chosen checkpoint {args.from_}", file=sys.stderr)
        else:
            try:
                finished = read_json(status_file).get("status") == "finished"
            except (OSError, ValueError, AttributeError) as err:
                finished = False  # no summary yet, or a damaged one: the resume rebuilds it
                if os.path.lexists(status_file):  # never silently (it is rebuilt from the checkpoints and logs)
                    warn(f"{status_file} cannot be read ({err}); the resume writes it afresh from "
                         f"the run's checkpoints and logs.")
            if finished:
                print(f"botorl: {root} has finished already; nothing to resume.", file=sys.stderr)
                summaries = [read_summary(r) for r in runs]
                try:
                    _print_summaries(summaries, single)
                except (KeyError, TypeError, ValueError, AttributeError):  # a summary edited by hand
                    print("\n".join(f"{r.root.name}: status {s.get('status')!r}" for r, s in zip(runs, summaries)))
                return 0
        d_raw = load_run_data(cfg, origin, args.allow_pickle)
        summaries = _execute(cfg, member_cfgs, root, runs, d_raw, resume=True, resume_from=args.from_)
    _print_summaries(summaries, single)
    return 0


def _print_result(result: dict) -> None:
    for k, v in result.items():
        print(f"{k:<15} {v:.4g}" if isinstance(v, float) else f"{k:<15} {v}")


def eval_main(argv: list[str]) -> int:
    args = tyro.cli(EvalArgs, args=argv, prog="botorl eval")
    check_ranges(args)
    setup_jax()
    # the checkpoint's identity before the task is made or data read (--policy: the contract's)
    run, cfg = read_run(args.dir, "evaluate", validate=True, entry=args.env,
                        before=None if args.policy else lambda r, c: check_resume_point(r.root, [c], args.checkpoint))
    if args.policy is not None:  # an exported model through onnxruntime (botorl/pipeline/export.py)
        if args.checkpoint is not None:
            raise ConfigError("--policy and --checkpoint: the model names its checkpoint (in FILE.onnx.json); give one.")
        with RunLock(run.root):
            _print_result(evaluate_exported(run, cfg, args.policy, episodes=args.episodes))
        return 0
    with RunLock(run.root), io_guard(run.root):
        _print_result(_eval(args, run, cfg))
    return 0


def _eval(args, run, cfg) -> dict:
    if args.episodes is not None:
        cfg = replace(cfg, eval=replace(cfg.eval, episodes=args.episodes))
    ckpt, name, state = check_checkpoint(run, cfg, args.checkpoint, data=True)
    spec = get_task(cfg.task)
    d = transform_dataset(cfg, spec, load_run_data(cfg, run.config, args.allow_pickle))
    like = stages.agent_template(cfg, state["stage"], d.obs_dim, d.action_dim, cfg.seed)
    agent = agent_file.load(ckpt.file(name, "agent.ckpt"), like=like)
    probe = QProbe(d.observations, d.actions, seed=Streams.PROBE, size=cfg.eval.q_pairs)
    with matmul_precision(cfg.precision):  # the run's own
        return evaluate_command(lambda o: agent.eval_actions(o[0])[None], cfg, cfg.eval.episodes,
                                {"checkpoint": name, "stage": state["stage"], "step": checkpoint_step(cfg, state)},
                                run.root / f"eval-{name}.json", q=lambda: probe(stages.q_fn(agent)))


def export_main(argv: list[str]) -> int:
    args = tyro.cli(ExportArgs, args=argv, prog="botorl export")
    out = Path(args.out) if args.out else Path(args.dir) / "policy.onnx"
    c = export_policy(args.dir, out, checkpoint=args.checkpoint, format=args.format, force=args.force, env=args.env)
    v = c["verification"]
    print(f"botorl: {c['task']} {c['method']} seed {c['seed']}, checkpoint {c['checkpoint']} (step {c['step']}) "
          f"-> {out} and {contract_path(out).name}", file=sys.stderr)
    print(f"model          {out}\ncontract       {contract_path(out)}\nobservations   (batch, {c['input']['shape'][1]}) "
          f"float32\nactions        (batch, {c['output']['shape'][1]}) float32\nverified       max |onnxruntime - "
          f"load_policy| = {v['max_abs_gap']:.2g} on {v['observations']} {v['source']} observations "
          f"(tolerance {v['tolerance']:g})\nsha256         {c['sha256']}")
    return 0

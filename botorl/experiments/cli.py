"""`botorl sweep` and `botorl report`: their flags and what each command prints (usage, resume,
the dip, held-out alpha selection: docs/running.md)."""

from __future__ import annotations

import dataclasses
import os
import shlex
import sys
from pathlib import Path
from typing import Annotated, Literal, Optional

import tyro

from botorl.configs.members import MAX_MEMBERS, SEED_LIMIT
from botorl.errors import ConfigError, Range, check_ranges
from botorl.experiments.grid import build_grid, load_grid_file, parse_seeds
from botorl.experiments.pairs import read_pairs_csv, write_paired_report
from botorl.experiments.report import make_report, select_alpha
from botorl.experiments.runs import find_runs
from botorl.experiments.sweep import USER_ERROR_EXIT, Sweep, SweepOptions, check_trial_configs, next_action
from botorl.pipeline.rundir import check_out


MAX_WORKERS = 1024  # parallel trials (local: processes, ray: CPUs of a local instance)
MAX_GRID_POINTS = 100_000  # points of Figure 5's env-step grid (its default 101)


@dataclasses.dataclass
class SweepArgs:
    """Run a grid of tasks x methods x seeds (x alphas for boto), one run directory per trial."""

    out: str
    """sweep directory; trial i lives in OUT/<task>/<method>[-<pretrain>]/[alpha<+0.50>/]seed<k>"""
    grid: Optional[str] = None
    """YAML file with tasks, methods, seeds, alphas, overrides, profile (the flags below win)"""
    tasks: Optional[str] = None
    """comma-separated task names"""
    methods: Optional[str] = None
    """comma-separated: boto, wsrl, calql, cql, iql, rlpd; boto-cql / boto-iql pick BOTO's pre-training"""
    seeds: Optional[str] = None
    """e.g. 0-4 (inclusive) or 0,1,2"""
    alphas: Optional[str] = None
    """boto only, e.g. -1:1:0.1 (stop included) or -0.5,0,0.5; None: each task's preset"""
    profile: Optional[str] = None
    """botorl run profile: quick, full or smoke"""
    set: tuple[str, ...] = ()
    """config overrides dotted.path=value, set in every trial's config as `botorl run --dotted.path value` sets it"""
    backend: Literal["sequential", "local", "ray"] = "local"
    """sequential: one at a time; local: --workers pinned processes (one per core unless given); ray: Ray tasks"""
    workers: Annotated[Optional[int], Range(1, MAX_WORKERS)] = None
    """parallel trials (local: each pinned to its own block of cores, C // workers of them; ray: CPUs of a local instance); None: one per usable core"""
    max_retries: Annotated[int, Range(0, 100)] = 2
    """a failed trial is resumed from its checkpoint at most this many times per invocation"""
    ray_address: Optional[str] = None
    """existing Ray cluster (e.g. auto or ray://head:10001); None: start a local instance"""
    trial_command: Optional[str] = None
    """command that stands in for `python -m botorl.cli` (testing); gets run/resume arguments"""
    population_size: Annotated[int, Range(1, MAX_MEMBERS, "members of one population")] = 1
    """train the trials of each (task, method, pre-training) K at a time as populations (one process,
    one jitted update for all members); 1: one process per trial"""
    share_pretraining: bool = True
    """a trial whose members' pre-training (same task, seed and settings) finished in --out starts
    from it, e.g. WSRL from BOTO's Cal-QL (the same numbers, computed once); --no-share-pretraining
    pre-trains every trial itself"""
    dry_run: bool = False
    """list the trials and what each would do (run / resume / done), launch nothing"""
    progress: bool = True
    """show a progress bar over trials"""


def _gather_set(argv: list[str]) -> list[str]:
    """Accept both `--set a=1 b=2` and `--set a=1 --set b=2` (tyro sees one --set)."""
    values: list[str] = []
    rest: list[str] = []
    in_set = False  # from a bare --set to the next flag
    for tok in argv:
        in_set = tok == "--set" or (in_set and not tok.startswith("--"))
        if tok.startswith("--set="):
            values.append(tok[len("--set="):])
        elif in_set:
            values += [tok] if tok != "--set" else []
        else:
            rest.append(tok)
    return rest + (["--set", *values] if values else [])


def sweep_main(argv: list[str]) -> int:
    args = tyro.cli(SweepArgs, args=_gather_set(list(argv)), prog="botorl sweep")
    check_ranges(args)
    check_out(args.out)
    file_fields = load_grid_file(args.grid) if args.grid else None
    grid = build_grid(file_fields, tasks=args.tasks, methods=args.methods, seeds=args.seeds, alphas=args.alphas,
                      overrides=list(args.set) if args.set else None, profile=args.profile)
    same = {f.name: getattr(args, f.name) for f in dataclasses.fields(SweepOptions) if hasattr(args, f.name)}
    command = shlex.split(args.trial_command) if args.trial_command else None
    sweep = Sweep(grid, SweepOptions(**{**same, "out": Path(args.out), "command": command}))
    if not args.trial_command:  # a stand-in command may know other tasks and options
        check_trial_configs(sweep)
    if args.dry_run:
        sweep.earlier_manifest()
        for trial in sweep.trials:
            print(f"{next_action(sweep.run_dir(trial)):6s}  {trial.relpath}")
        print(f"{len(sweep.trials)} trials in {sweep.out}")
        return 0
    manifest = sweep.run()
    states = {t.relpath: manifest["trials"][t.relpath] for t in sweep.trials}
    failed = [tid for tid, e in states.items() if e["state"] != "finished"]
    n = len(states)
    print(f"botorl sweep: {n - len(failed)}/{n} trials finished in {sweep.out}")
    # a trial that exited 2 refused its input (its directory, its settings): retrying cannot help
    refused = [tid for tid in failed if states[tid].get("returncode") == USER_ERROR_EXIT]
    for tid in failed:
        lines = (states[tid].get("error") or states[tid]["state"]).splitlines()
        reason = lines[0] + (f" {lines[-1].strip()}" if tid in refused and len(lines) > 1 else "")
        print(f"  FAILED {tid}: {reason} (log: {sweep.out / tid / 'sweep-trial.log'})", file=sys.stderr)
    if failed:
        print("botorl sweep: start the same command again to retry the failed trials (finished ones are kept)"
              + ("; those refused need their directory or settings fixed first." if refused else "."), file=sys.stderr)
    return 0 if not failed else USER_ERROR_EXIT if len(refused) == len(failed) else 1


@dataclasses.dataclass
class ReportArgs:
    """Table 1, Figure 5 and the alpha-sensitivity figure from finished run directories."""

    dirs: tyro.conf.Positional[tuple[str, ...]]
    """run or sweep directories, searched recursively for summary.json"""
    out: Optional[str] = None
    """output folder (None: the first DIR/report)"""
    select_alpha: bool = False
    """pick alpha per task from an alpha sweep and print the preset lines"""
    bootstrap: int = 2000
    """bootstrap resamples for the IQM confidence intervals"""
    confidence: float = 0.95
    """confidence level of the IQM intervals"""
    seed: Annotated[int, Range(0, SEED_LIMIT - 1)] = 0
    """seed of the bootstrap"""
    grid_points: Annotated[int, Range(2, MAX_GRID_POINTS)] = 101
    """points of the common env-step grid of Figure 5"""
    dip_window: Annotated[int, Range(0, 10**12)] = 10_000
    """the dip: lowest success over evaluations with 0 <= env_step <= this, minus success at step 0"""
    select_seeds: Optional[str] = None
    """seeds that choose alpha (e.g. 0-3 or 0,2,4); None: the first half of each alpha's sorted seeds"""
    report_seeds: Optional[str] = None
    """seeds on which the chosen alpha's score is reported (None: every seed not in --select-seeds)"""
    pairs_from: tuple[str, ...] = ()
    """paired.csv files of earlier reports: their pairs join the pairs of DIRS (a study reported
    population by population, whose run directories are gone); DIRS may then be empty"""


def report_main(argv: list[str]) -> int:
    args = tyro.cli(ReportArgs, args=list(argv), prog="botorl report")
    check_ranges(args)
    if args.out is not None:
        check_out(args.out)
    extra_pairs = []
    for p in args.pairs_from:
        try:
            extra_pairs += read_pairs_csv(Path(os.path.realpath(p)))  # a regular file of bounded size
        except (OSError, KeyError, ValueError, TypeError) as err:
            raise ConfigError(f"--pairs-from {p}: not a paired.csv that `botorl report` wrote ({err}).") from None
    if not args.dirs and not extra_pairs:
        raise ConfigError("botorl report needs at least one run or sweep directory (or --pairs-from paired.csv files).")
    stats = dict(n_boot=args.bootstrap, confidence=args.confidence, seed=args.seed)
    if not args.dirs:
        if not args.out:
            raise ConfigError("botorl report --pairs-from without run directories needs --out.")
        for f in write_paired_report(extra_pairs, Path(args.out), sources=args.pairs_from, **stats):
            print(f"  wrote {f}")
        return 0
    dirs = [Path(d) for d in args.dirs]
    runs, skipped = find_runs(dirs)
    if not runs:  # an empty report would look like a result; say why there is none
        why = "; ".join(f"{s.path}: {s.reason}" for s in skipped[:5]) or "no run directory (summary.json) under them"
        raise ConfigError(f"no finished run in {', '.join(map(str, args.dirs))} ({why}). Give the "
                          f"--out of `botorl run` or a `botorl sweep` folder whose runs have finished.")
    select_seeds = _seed_flag("--select-seeds", args.select_seeds)
    report_seeds = _seed_flag("--report-seeds", args.report_seeds)
    if args.select_alpha:  # refuse before writing anything when held-out selection is impossible
        select_alpha(runs, select_seeds=select_seeds, report_seeds=report_seeds, **stats)
    out = Path(args.out) if args.out else Path(args.dirs[0]) / "report"
    # out inside a DIR reported on (DIR/report, the default): no link on the way down from DIR
    root = next((Path(d) for d in args.dirs if Path(os.path.abspath(out)).is_relative_to(os.path.abspath(d))), None)
    result = make_report(dirs, out, grid_points=args.grid_points, dip_window=args.dip_window, select_seeds=select_seeds,
                         report_seeds=report_seeds, extra_pairs=extra_pairs, root=root, **stats)
    print(result.summary_text())
    if args.select_alpha and result.selection is not None:
        print(result.selection.text())
    return 0


def _seed_flag(flag: str, value: Optional[str]) -> Optional[list[int]]:
    if value is None:
        return None
    try:
        return parse_seeds(value)
    except ConfigError:
        raise ConfigError(
            f"{flag} {value!r} is not a seed set; use a range like 0-3 (inclusive), a list "
            "like 0,2,4, or both (0-2,7); seeds are >= 0."
        ) from None

"""`botorl study run STUDY.toml` and `botorl study report STUDY.toml` (docs/running.md, "Writing a study")."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated, Optional

import tyro

from botorl.errors import ConfigError
from botorl.experiments.study import StudyRun, load_study

USAGE = """usage: botorl study run STUDY.toml [--lanes K] [--unfrozen] [--workers N]
       botorl study report STUDY.toml [--out DIR]

run:    every block's arms as `botorl sweep`s, in the file's order; the same command resumes
report: the analysis from the records alone (markdown, CSV, a figure, the sweeps as commands)"""


@dataclasses.dataclass
class RunArgs:
    """Run every block's arms of a study file as sweeps, resumably (the same command continues)."""

    study: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="STUDY.toml")]
    """the study file (TOML)"""
    lanes: int = 1
    """arms run side by side (an arm that reuses a pre-training waits for the arm that makes it)"""
    unfrozen: bool = False
    """run although botorl is not at the study's frozen commit with a clean tree; recorded in the results"""
    workers: Optional[int] = None
    """each sweep's --workers (None: one per usable core, as a sweep chooses)"""
    trial_command: Optional[str] = None
    """each sweep's --trial-command (testing)"""


@dataclasses.dataclass
class ReportArgs:
    """Write a study's analysis from its committed records alone."""

    study: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="STUDY.toml")]
    """the study file (TOML)"""
    out: Optional[str] = None
    """output folder (None: analysis/ beside the study file)"""


def main(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE)
        return 0
    what, rest = argv[0], argv[1:]
    if what == "run":
        args = tyro.cli(RunArgs, args=rest, prog="botorl study run")
        return StudyRun(load_study(args.study), lanes=args.lanes, unfrozen=args.unfrozen, workers=args.workers,
                        trial_command=args.trial_command).run()
    if what == "report":
        args = tyro.cli(ReportArgs, args=rest, prog="botorl study report")
        from botorl.experiments.study_report import report  # lazy: matplotlib and the report's code, only for `report`

        study = load_study(args.study)
        for f in report(study, Path(args.out) if args.out else study.path.parent / "analysis"):
            print(f"  wrote {f}")
        return 0
    raise ConfigError(f"unknown action {what!r}; use `run` or `report`.\n{USAGE}")

"""A study: a plan fixed in a file before its first run (``STUDY.toml``), run and reported by
`botorl study run` and `botorl study report` (the format and the workflow: docs/running.md,
"Writing a study").

The file names the frozen commit, the tasks, profile and shared settings, the blocks (seed
ranges), the arms (each a `botorl sweep` of one method: which arm pre-trains a block and which
start from its pre-training), the comparisons and the bootstrap. ``run`` runs every block's arms
as sweeps, one folder each (``<runs>/<block>/<arm>``), resumable: what is done is read from
``<results>/study-run.json`` and the sweeps themselves, so the same command continues after a
kill -9 at any point. After each arm it checks that the arm starts from the very pre-training
it names (``summary.json``'s ``pretrain_sha256``) and copies each run's small records into
``<results>/<block>/<arm>/<task>/seed<k>/``, which the report reads and a commit keeps.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import math
import os
import re
import subprocess
import sys
import time
import tomllib
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from botorl.errors import BotorlError, ConfigError, Interrupted
from botorl.experiments import child
from botorl.experiments.grid import build_grid, format_alpha, parse_methods, parse_overrides, parse_seeds
from botorl.experiments.runs import find_runs
from botorl.experiments.sweep import check_trial_configs
from botorl.io import JSON_LIMIT, atomic_write_bytes, atomic_write_json, read_bounded_bytes, read_json_object
from botorl.pipeline.provenance import botorl_commit
from botorl.pipeline.rundir import RunLock

# the endpoints a study may name, per run (study_report.endpoints_of computes them)
ENDPOINTS = ("dip", "success_10k", "window_mean", "success_0", "lowest", "success_final")
RECORDS = ("config.json", "summary.json", "eval.csv")  # what is kept of a run; not checkpoints or metrics
STATE = "study-run.json"  # in the results folder: what ran, when, on which commit, and every deviation

_NAME = re.compile(r"[a-z0-9][a-z0-9-]*")
_KEY = re.compile(r"[a-z0-9_+]+")
_COMMIT = re.compile(r"[0-9a-f]{7,40}")


@dataclasses.dataclass(frozen=True)
class Block:
    name: str
    seeds: tuple[int, ...]
    paired_csv: Path | None = None  # a legacy block: its records are this `botorl report` file


@dataclasses.dataclass(frozen=True)
class Arm:
    key: str
    label: str
    method: str  # a sweep method name (boto, wsrl, boto-cql, ...)
    alpha: float | None = None
    set: tuple[str, ...] = ()
    pretrains: bool = False
    reuses: str | None = None  # the arm whose pre-training this one starts from, in the same block


@dataclasses.dataclass(frozen=True)
class Study:
    path: Path
    name: str
    question: str
    commit: str
    tasks: tuple[str, ...]
    profile: str
    set: tuple[str, ...]
    population_size: int | None
    runs: Path
    results: Path
    reference: str
    blocks: tuple[Block, ...]
    arms: tuple[Arm, ...]
    endpoints: tuple[str, ...]
    primary: tuple[tuple[str, str], ...]
    secondary: tuple[tuple[str, str], ...]
    floors: tuple[tuple[str, str], ...]
    equivalence: dict[tuple[str, str], float]
    window_end: float
    n_boot: int
    boot_seed: int

    def arm(self, key: str) -> Arm:
        return next(a for a in self.arms if a.key == key)

    def arm_dir(self, block: Block, arm: Arm) -> Path:
        return self.runs / block.name / arm.key

    def records_dir(self, block: Block, arm: Arm) -> Path:
        return self.results / block.name / arm.key

    def sweep_args(self, block: Block, arm: Arm, runs: Path | str | None = None) -> list[str]:
        """The `botorl sweep` arguments of one arm in one block (``runs``: the runs folder as
        written, for a command a reader runs by hand)."""
        runs = Path(runs) if runs is not None else self.runs
        args = ["--tasks", ",".join(self.tasks), "--profile", self.profile, "--methods", arm.method]
        if arm.alpha is not None:
            args.append(f"--alphas={format_alpha(arm.alpha)}")
        args += ["--seeds", seeds_text(block.seeds),
                 "--population-size", str(self.population_size or len(block.seeds)),
                 "--out", str(runs / block.name / arm.key)]
        sets = list(self.set) + list(arm.set)
        if arm.reuses:
            sets.append(f"pretrained={runs / block.name / arm.reuses}")
        return args + (["--set", *sets] if sets else [])


def arm_config(study: Study, arm: Arm, task: str):
    """The RunConfig an arm's sweep gives its first seed on ``task``, built and checked as
    `botorl sweep` does before it launches anything; a ConfigError names the arm."""
    grid = build_grid(tasks=task, methods=arm.method, seeds=[study.blocks[0].seeds[0]],
                      alphas=None if arm.alpha is None else [arm.alpha], overrides=list(study.set) + list(arm.set),
                      profile=study.profile)
    built: dict[str, Any] = {}
    sweep = SimpleNamespace(trials=grid.trials()[:1], config=lambda t: built.setdefault("cfg", grid.config(t)))
    try:
        check_trial_configs(sweep)
    except ConfigError as err:
        raise ConfigError(f"{study.path}: [[arms]] {arm.key} on {task}: {err}") from None
    return built["cfg"]


def seeds_text(seeds: tuple[int, ...]) -> str:
    """``200-207`` for a run of seeds, else ``1,3,5``."""
    if len(seeds) > 1 and list(seeds) == list(range(seeds[0], seeds[0] + len(seeds))):
        return f"{seeds[0]}-{seeds[-1]}"
    return ",".join(map(str, seeds))


# ----------------------------------------------------------------------------- reading the file

class _Table:
    """One TOML table, read field by field: every error names the file and the field."""

    def __init__(self, path: Path, where: str, data: Any, known: tuple[str, ...]):
        self.path, self.where = path, where
        if not isinstance(data, dict):
            self.fail("", f"must be a table, got {type(data).__name__}")
        if unknown := sorted(set(data) - set(known)):
            self.fail(unknown[0], f"is not a field of {where} (known: {', '.join(known)})")
        self.data = data

    def fail(self, field: str, what: str):
        raise ConfigError(f"{self.path}: {self.where}{' ' + field if field else ''} {what}.")

    def get(self, field: str, kind: type | tuple, default: Any = ..., *, check=None, hint: str = "") -> Any:
        if field not in self.data:
            if default is ...:
                self.fail(field, f"is missing{'; ' + hint if hint else ''}")
            return default
        value = self.data[field]
        kinds = kind if isinstance(kind, tuple) else (kind,)
        if not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds):  # true is no number here
            names = {str: "text", int: "a whole number", float: "a number", bool: "true or false", list: "a list",
                     dict: "a table"}
            self.fail(field, f"must be {' or '.join(names.get(k, k.__name__) for k in kinds)}, got {value!r}")
        if check is not None and not check(value):
            self.fail(field, f"is {value!r}; {hint}")
        return value

    def strings(self, field: str) -> tuple[str, ...]:
        value = self.get(field, list, [])
        if not all(isinstance(v, str) for v in value):
            self.fail(field, "must be a list of strings")
        return tuple(value)


def load_study(path: str | Path) -> Study:
    """The study file, checked whole: a ConfigError (exit 2) names the first wrong field."""
    path = Path(path)
    try:
        raw = tomllib.loads(read_bounded_bytes(path, JSON_LIMIT).decode())
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such study file.") from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: not valid TOML ({err}).") from None
    except (OSError, ValueError) as err:  # ValueError: not a regular file, too large, not UTF-8
        raise ConfigError(f"{path}: cannot read the study file ({err}).") from None
    top = _Table(path, "the file:", raw, ("study", "blocks", "arms", "analysis"))
    s = _Table(path, "[study]", top.get("study", dict, hint="start the file with a [study] table"),
               ("name", "question", "commit", "tasks", "profile", "set", "population_size", "runs", "results",
                "reference"))
    name = s.get("name", str, check=_NAME.fullmatch, hint="use lower-case letters, digits and '-'")
    commit = s.get("commit", str, check=_COMMIT.fullmatch,
                   hint="give the frozen commit as 7 to 40 hex digits (git rev-parse --short HEAD)").lower()
    tasks = s.strings("tasks")
    if not tasks:
        s.fail("tasks", "is missing or empty; name the task(s) every arm runs")
    _overrides(s, "set", s.strings("set"))
    blocks = _blocks(path, top.get("blocks", list, hint="add [[blocks]] tables with name and seeds"))
    arms = _arms(path, top.get("arms", list, hint="add [[arms]] tables"), s)
    keys = [a.key for a in arms]
    reference = s.get("reference", str, check=lambda k: k in keys, hint=f"name one of the arms ({', '.join(keys)})")
    runs = Path(s.get("runs", str, f"study/{name}"))
    results = path.parent / s.get("results", str, "results")
    size = s.get("population_size", int, None, check=lambda n: n >= 1, hint="give 1 or more")
    a = _Table(path, "[analysis]", top.get("analysis", dict, {}),
               ("endpoints", "primary", "secondary", "floors", "equivalence", "window_end", "n_boot", "boot_seed"))
    endpoints = a.strings("endpoints") or ("dip", "success_10k")
    if unknown := [e for e in endpoints if e not in ENDPOINTS]:
        a.fail("endpoints", f"names {unknown[0]!r}, which is not an endpoint (known: {', '.join(ENDPOINTS)})")
    comps = {f: tuple(_comparison(a, f, c, keys) for c in a.strings(f)) for f in ("primary", "secondary", "floors")}
    margins = {}
    for text, margin in a.get("equivalence", dict, {}).items():
        c = _comparison(a, "equivalence", text, keys)
        if c not in comps["primary"] + comps["secondary"]:
            a.fail("equivalence", f"names {text!r}, which is no primary or secondary comparison")
        if isinstance(margin, bool) or not isinstance(margin, (int, float)) or not margin > 0:
            a.fail("equivalence", f"margin of {text!r} is {margin!r}; give a positive number")
        margins[c] = float(margin)
    return Study(
        path=path, name=name, question=s.get("question", str, ""), commit=commit, tasks=tasks,
        profile=s.get("profile", str, hint="name the botorl run profile (quick, mid, full, smoke)"),
        set=s.strings("set"), population_size=size, runs=runs, results=results, reference=reference,
        blocks=blocks, arms=arms, endpoints=endpoints, **comps, equivalence=margins,
        window_end=float(a.get("window_end", (int, float), 10_000, check=lambda v: v > 0, hint="give env steps > 0")),
        n_boot=a.get("n_boot", int, 10_000, check=lambda n: 1 <= n <= 1_000_000, hint="give 1 to 1,000,000"),
        boot_seed=a.get("boot_seed", int, 0),
    )


def _overrides(t: _Table, field: str, values: tuple[str, ...]) -> None:
    try:
        parse_overrides(list(values))
    except ConfigError as err:
        t.fail(field, f"has a bad override ({err})")


def _comparison(t: _Table, field: str, text: str, keys: list[str]) -> tuple[str, str]:
    x, sep, y = text.partition("-")
    if not sep or not x or not y:
        t.fail(field, f"names {text!r}; write a comparison as 'x-y', arm x minus arm y")
    for k in (x, y):
        if k not in keys:
            t.fail(field, f"names {text!r}, but {k!r} is no arm (arms: {', '.join(keys)})")
    if x == y:
        t.fail(field, f"compares arm {x!r} with itself")
    return x, y


def _blocks(path: Path, items: list) -> tuple[Block, ...]:
    blocks: list[Block] = []
    for i, item in enumerate(items):
        t = _Table(path, f"[[blocks]] #{i + 1}", item, ("name", "seeds", "paired_csv"))
        name = t.get("name", str, check=_NAME.fullmatch, hint="use lower-case letters, digits and '-'")
        raw = t.get("seeds", (str, int, list))  # a wrong type is its own message, not nested below
        try:
            seeds = tuple(parse_seeds(raw))
        except ConfigError as err:
            t.fail("seeds", f"is not a seed set ({err})")
        csv = t.get("paired_csv", str, None)
        for other in blocks:
            if other.name == name:
                t.fail("name", f"{name!r} is used by an earlier block")
            if shared := sorted(set(other.seeds) & set(seeds)):
                t.fail("seeds", f"overlap block {other.name!r}'s (both hold seed {shared[0]}); blocks must not overlap")
        blocks.append(Block(name, seeds, None if csv is None else path.parent / csv))
    if not blocks:
        raise ConfigError(f"{path}: the file has no [[blocks]]; add at least one with name and seeds.")
    return tuple(blocks)


def _arms(path: Path, items: list, study: _Table) -> tuple[Arm, ...]:
    arms: list[Arm] = []
    for i, item in enumerate(items):
        t = _Table(path, f"[[arms]] #{i + 1}", item, ("key", "label", "method", "alpha", "set", "pretrains", "reuses"))
        key = t.get("key", str, check=_KEY.fullmatch, hint="use lower-case letters, digits, '_' and '+'")
        if any(a.key == key for a in arms):
            t.fail("key", f"{key!r} is used by an earlier arm")
        method = t.get("method", str)
        try:
            ((m, _),) = parse_methods(method)
        except (ConfigError, ValueError) as err:
            t.fail("method", f"is not one sweep method ({err})")
        alpha = t.get("alpha", (int, float), None)
        if alpha is not None and (m != "boto" or not math.isfinite(alpha)):
            t.fail("alpha", "is BOTO's bias controller: give a finite number, on a boto arm only")
        sets = t.strings("set")
        _overrides(t, "set", sets)
        pretrains, reuses = t.get("pretrains", bool, False), t.get("reuses", str, None)
        if pretrains == (reuses is not None):
            t.fail("pretrains", "or reuses: give exactly one (pretrains = true, or reuses = \"<arm that pre-trains>\")")
        arms.append(Arm(key, t.get("label", str, key), method, None if alpha is None else float(alpha), sets,
                        pretrains, reuses))
    if not arms:
        raise ConfigError(f"{path}: the file has no [[arms]]; add at least one.")
    makers = [a.key for a in arms if a.pretrains]
    for i, a in enumerate(arms):
        if a.reuses is not None and a.reuses not in makers:
            raise ConfigError(f"{path}: [[arms]] #{i + 1} reuses {a.reuses!r}, but no arm of that key pre-trains "
                              f"(arms that do: {', '.join(makers) or 'none'}); set pretrains = true on it.")
    return tuple(arms)


# ----------------------------------------------------------------------------- running

def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def frozen_deviation(study: Study, commit: str | None) -> str | None:
    """Why the installed botorl is not the study's frozen code (None: it is)."""
    if commit is None:
        return f"botorl's commit cannot be read (not a git checkout); the study is frozen at {study.commit}"
    head, dirty = commit.removesuffix("+dirty"), commit.endswith("+dirty")
    if not head.startswith(study.commit):
        return f"botorl is at commit {head[:12]}, the study is frozen at {study.commit}"
    if dirty:
        return f"botorl's tree at {study.commit} has uncommitted changes (+dirty)"
    return None


class StudyRun:
    """One invocation of `botorl study run`."""

    def __init__(self, study: Study, *, lanes: int = 1, unfrozen: bool = False, workers: int | None = None,
                 trial_command: str | None = None):
        if lanes < 1:
            raise ConfigError(f"--lanes must be 1 or more, got {lanes}.")
        self.study, self.lanes, self.workers, self.trial_command = study, lanes, workers, trial_command
        self.commit = botorl_commit()
        deviation = frozen_deviation(study, self.commit)
        if deviation and not unfrozen:
            raise ConfigError(f"{study.path}: {deviation}. Check out the frozen commit with a clean tree, or run with "
                              "--unfrozen, which records the deviation in the results.")
        self.deviation = deviation
        for arm in study.arms:  # a typo in a task or an override fails now, not in every block's sweep
            for task in study.tasks:
                arm_config(study, arm, task)
        self.state_path = study.results / STATE
        self.state = read_json_object(self.state_path) or {}

    def jobs(self) -> list[tuple[Block, Arm]]:
        """Every block's arms in the file's order (legacy blocks have nothing to run)."""
        return [(b, a) for b in self.study.blocks if b.paired_csv is None for a in self.study.arms]

    def done(self, block: Block, arm: Arm) -> bool:
        return bool(self.state.get("arms", {}).get(f"{block.name}/{arm.key}", {}).get("ended"))

    def _save(self) -> None:
        atomic_write_json(self.state_path, self.state)

    def run(self) -> int:
        s = self.study
        lock = RunLock(s.runs, ".study.lock", f"pid {os.getpid()}", lambda who: BotorlError(
            f"Another `botorl study run` ({who}) is running {s.runs}. Wait for it, or stop it and start again."))
        lock.acquire()
        try:
            self.state.setdefault("study", s.name)
            self.state.setdefault("frozen_commit", s.commit)
            self.state.setdefault("invocations", []).append(
                {"started": _now(), "commit": self.commit, "lanes": self.lanes, "unfrozen": self.deviation})
            self.state.setdefault("arms", {})
            self._save()
            return self._loop()
        finally:
            lock.release()

    def _loop(self) -> int:
        pending = [j for j in self.jobs() if not self.done(*j)]
        running: dict[tuple[Block, Arm], subprocess.Popen] = {}
        failed: list[str] = []
        codes: set[int] = set()
        try:
            while (pending and not failed) or running:
                ready = [] if failed else [j for j in pending if self._ready(*j)]  # after a failure: no new arm
                for job in ready[: self.lanes - len(running)]:
                    pending.remove(job)
                    running[job] = self._start(*job)
                for job, proc in list(running.items()):
                    if (code := proc.poll()) is not None:
                        del running[job]
                        if code == 0:
                            self._finish(*job)
                        else:
                            codes.add(code)
                            failed.append(f"{job[0].name}/{job[1].key} (sweep exit {code}; log {self._log(*job)})")
                time.sleep(0.2)
        except BaseException as err:
            if isinstance(err, Interrupted):
                err.how = "the same `botorl study run` command (finished arms are kept, the rest resume)"
            for proc in running.values():  # each sweep stops its trials at a checkpoint; the next run resumes
                proc.terminate()
            for proc in running.values():
                proc.wait()
            raise
        if failed:
            print(f"botorl study: {', '.join(failed)} failed; start the same command again to retry "
                  "(finished runs are kept).", file=sys.stderr)
            return 2 if 2 in codes else 1  # 2: a sweep refused its settings, which a retry cannot mend
        print(f"botorl study: every arm of {self.study.name} finished; records in {self.study.results}")
        return 0

    def _ready(self, block: Block, arm: Arm) -> bool:
        """An arm that reuses a pre-training runs once the arm that makes it has finished."""
        return arm.reuses is None or self.done(block, self.study.arm(arm.reuses))

    def _log(self, block: Block, arm: Arm) -> Path:
        return self.study.runs / block.name / f"{arm.key}.log"

    def _start(self, block: Block, arm: Arm) -> subprocess.Popen:
        args = self.study.sweep_args(block, arm)
        entry = self.state["arms"].setdefault(f"{block.name}/{arm.key}", {})
        entry.update(command=["botorl", "sweep", *args], started=_now(), ended=None)  # as a reader would type it
        entry.setdefault("first_started", entry["started"])
        self._save()
        log = self._log(block, arm)
        log.parent.mkdir(parents=True, exist_ok=True)
        print(f"botorl study: {block.name}/{arm.key} ({arm.label}) started; log {log}", flush=True)
        args += ["--no-progress"] + ([] if self.workers is None else ["--workers", str(self.workers)])
        args += [] if self.trial_command is None else ["--trial-command", self.trial_command]
        # dies with the study (PR_SET_PDEATHSIG), so a kill -9 of it leaves no sweep behind
        cmd = child.launcher([sys.executable, "-m", "botorl.cli", "sweep", *args], os.getpid())
        with open(log, "ab") as f:
            return subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)

    def _finish(self, block: Block, arm: Arm) -> None:
        """Check the arm's pre-training digests, copy its records, mark it done (in that order:
        a kill before the mark repeats the copy, which writes the same files)."""
        s = self.study
        runs, skipped = find_runs([s.arm_dir(block, arm)])
        if skipped or len(runs) != len(s.tasks) * len(block.seeds):
            raise BotorlError(f"{block.name}/{arm.key}: the sweep ended but {len(runs)} of "
                              f"{len(s.tasks) * len(block.seeds)} runs finished ({s.arm_dir(block, arm)}).")
        digests = {f"{r.task}/seed{r.seed}": r.pretrain_sha256 for r in runs}
        if arm.reuses:
            want = self.state["arms"][f"{block.name}/{arm.reuses}"]["pretrain_sha256"]
            if bad := sorted(k for k, d in digests.items() if d != want.get(k)):
                raise BotorlError(
                    f"{block.name}/{arm.key}: {len(bad)} run(s) do not start from the pre-training of arm "
                    f"{arm.reuses!r} (pretrain_sha256 differs, e.g. {bad[0]}: {str(digests[bad[0]])[:12]} against "
                    f"{str(want.get(bad[0]))[:12]}). A block's arms must start from one pre-training; re-run the "
                    "block whole under a new name.")
        for r in runs:
            dest = s.records_dir(block, arm) / r.task / f"seed{r.seed}"
            for name in RECORDS:
                atomic_write_bytes(dest / name, read_bounded_bytes(r.path / name, 64 << 20))
        entry = self.state["arms"][f"{block.name}/{arm.key}"]
        entry.update(ended=_now(), runs=len(runs), pretrain_sha256=digests)
        self._save()
        print(f"botorl study: {block.name}/{arm.key} finished; {len(runs)} runs' records in "
              f"{s.records_dir(block, arm)}", flush=True)

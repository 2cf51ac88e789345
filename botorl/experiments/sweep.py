"""Run every trial of a grid as its own `botorl run` process, and survive being killed.

What a trial needs next is read from its run directory every time (``next_action``), never
trusted from memory, so starting the same command again after a kill finishes the sweep;
``sweep.json`` (written atomically) records the grid and each trial's state, launches and last
end. Backends (``start``, ``launch``, ``poll``, ``abort``, ``close``): backend_local.py
(``sequential``, ``local``) and backend_ray.py (``ray``). With ``population_size`` K > 1 the unit
of work is a population (grid.group_populations). Trials die with the sweep (child.py); one that
outlives it is found through its pid file and stopped on restart (backend_local.stop_orphan).
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import io
import os
import re
import signal
import socket
import sys
import time
from collections import deque
from pathlib import Path
from typing import Any, Sequence

from tqdm import tqdm

from botorl.configs.members import population
from botorl.configs.methods import get_method
from botorl.configs.schema import to_dict
from botorl.errors import BotorlError, ConfigError, Interrupted
from botorl.experiments.backend_local import TRIAL_PID, LocalBackend, stop_orphan
from botorl.experiments.backend_ray import RayBackend
from botorl.experiments.backend_ray import cleanup_previous as cleanup_previous_ray
from botorl.experiments.grid import Grid, Trial, group_populations
from botorl.experiments.runs import group_by
from botorl.io import (SWEEP_JSON_LIMIT, append_text, atomic_write_json, own_folder, read_bounded, read_json_bounded,
                       read_json_object)
from botorl.pipeline import preempt, shared_pretrain
from botorl.pipeline.rundir import POPULATION_FILE, RunLock
from botorl.pipeline.tracking import require_wandb

MANIFEST = "sweep.json"
LOCKFILE = ".sweep.lock"
TRIAL_LOG = "sweep-trial.log"  # stdout+stderr of every attempt, appended
TRIAL_CONFIG = "sweep-trial-config.json"  # the config `botorl run --config` reads (configs.schema.to_dict)
USER_ERROR_EXIT = 2  # BotorlError: retrying cannot help

BACKENDS = ("sequential", "local", "ray")

DEFAULT_COMMAND = (sys.executable, "-m", "botorl.cli")


def _now() -> str:
    return _dt.datetime.now().isoformat(timespec="seconds")


def run_status(run_dir: Path) -> str | None:
    """A run's summary.json status, or a population directory's population.json status."""
    summary = read_json_object(Path(run_dir) / "summary.json") or read_json_object(Path(run_dir) / POPULATION_FILE)
    return None if summary is None else str(summary.get("status"))


def next_action(run_dir: Path) -> str:
    """'done', 'resume' or 'run': config.json decides (`botorl run` refuses a directory that has
    one, and `botorl resume` of a run killed before its first checkpoint starts it over)."""
    if run_status(run_dir) == "finished":
        return "done"
    if (Path(run_dir) / "config.json").exists() or (Path(run_dir) / POPULATION_FILE).exists():
        return "resume"
    return "run"


def trial_command(cfg, run_dir: Path, command: Sequence[str] | None = None,
                  share_in: Path | None = None) -> tuple[str, list[str]]:
    """(action, command) of the trial in ``run_dir`` (``cfg`` None: a stand-in command's own task);
    with ``share_in`` a new trial starts from pre-training finished there."""
    prefix = list(command or DEFAULT_COMMAND)
    action = next_action(run_dir)
    # no progress bars: a trial's output goes to its log file, where tqdm's redraws pile up
    if action == "resume":
        consent = ["--allow-pickle"] if cfg is not None and same_data(cfg, run_dir) else []
        return action, prefix + ["resume", str(run_dir), "--no-progress", *consent]
    shared = (["--pretrained", str(share_in)] if cfg is not None and share_in is not None
              and shares_pretraining(cfg, share_in) else [])
    return action, prefix + ["run", "--config", str(run_dir / TRIAL_CONFIG), *shared, "--out", str(run_dir),
                             "--no-progress"]


def same_data(cfg, run_dir: Path) -> bool:
    """Whether the trial's run directory reads its offline data (data.path, data.demos) from where
    ``cfg`` says: then its `botorl resume` gets --allow-pickle, as the user named that data when
    starting the sweep (a pickle-format task resumes); a path only the directory names stays refused."""
    pop = read_json_object(Path(run_dir) / POPULATION_FILE)
    saved = pop.get("config") if pop is not None else read_json_object(Path(run_dir) / "config.json")
    data = saved.get("data") if isinstance(saved, dict) else None
    return isinstance(data, dict) and data.get("path") == cfg.data.path and data.get("demos") == cfg.data.demos


def shares_pretraining(cfg, directory: Path) -> bool:
    """Whether every member of ``cfg`` has a finished pre-training with its settings under
    ``directory`` (BOTO's, for WSRL at the same seeds), so that it can start from it."""
    return (cfg.pretrained is None and "pretrain" in get_method(cfg.method).stages
            and shared_pretrain.match(population(cfg)[1], directory, strict=False) is not None)


@dataclasses.dataclass
class SweepOptions:
    out: Path
    backend: str = "local"
    workers: int | None = None  # default: the cores this process may use
    max_retries: int = 2
    ray_address: str | None = None
    command: Sequence[str] | None = None  # trial command prefix; default `python -m botorl.cli`
    progress: bool = True
    poll_interval: float = 0.25
    population_size: int = 1  # > 1: trials grouped into populations, one `botorl run --seeds` each
    share_pretraining: bool = True  # a new trial starts from pre-training finished in `out` (shared_pretrain.py)


class Sweep:
    """One invocation of `botorl sweep` over a grid, in `options.out`."""

    def __init__(self, grid: Grid, options: SweepOptions):
        if options.backend not in BACKENDS:
            raise ConfigError(f"Unknown sweep backend {options.backend!r}; use one of {', '.join(BACKENDS)}.")
        if options.max_retries < 0:
            raise ConfigError(f"--max-retries must be >= 0, got {options.max_retries}.")
        self.grid = grid
        self.opt = options
        self.out = Path(options.out).resolve()
        # the units of work: trials, or populations of trials (grid.PopulationJob) that
        # quack like trials (relpath, fields, to_json)
        size = options.population_size
        self.trials = grid.trials() if size <= 1 else group_populations(grid.trials(), size)
        self.configs: dict[str, Any] = {}  # relpath -> RunConfig, each built once (config)
        self.manifest: dict[str, Any] = {}
        # two sweeps in one directory would launch every trial twice
        stamp = f"pid {os.getpid()} on {socket.gethostname()}"
        self._lock = RunLock(self.out, LOCKFILE, stamp, lambda who: BotorlError(
            f"Another sweep ({who}) is running in {self.out}. Wait for it to end, or stop it "
            "and start this command again: finished trials are kept and the rest resume."))
        self._pbar = None
        self.backend = (RayBackend if options.backend == "ray" else LocalBackend)(self)

    def run_dir(self, trial: Trial) -> Path:
        return self.out / trial.relpath

    def config(self, trial: Trial):
        """The trial's RunConfig, built once; None for a stand-in command's own task."""
        if trial.relpath not in self.configs:
            try:
                self.configs[trial.relpath] = self.grid.config(trial)
            except BotorlError:
                if not self.opt.command:
                    raise
                self.configs[trial.relpath] = None
        return self.configs[trial.relpath]

    def _load_manifest(self) -> None:
        old, grid = self.earlier_manifest(), self.grid.to_json()
        cleanup_previous_ray(old, self.out)  # after the checks: a refused command touches no process
        trials = old.get("trials", {})
        history = list(old.get("invocations", [])) + [{"started": _now(), "grid": grid, "backend": self.opt.backend}]
        self.manifest = {
            "version": 1,
            "grid": grid,
            "backend": self.opt.backend,
            "command": list(self.opt.command or DEFAULT_COMMAND),
            "max_retries": self.opt.max_retries,
            "invocations": history,
            "updated": _now(),
            "trials": trials,
        }
        for trial in self.trials:
            entry = trials.setdefault(trial.relpath, {})
            entry.update(trial.to_json())
            entry["dir"] = trial.relpath
            entry.setdefault("launches", 0)
            entry["failures_this_invocation"] = 0
            entry["state"] = "finished" if run_status(self.run_dir(trial)) == "finished" else "pending"
            if entry["state"] == "finished" and not entry.get("ended"):  # the last sweep was killed
                with contextlib.suppress(OSError):
                    mtime = (self.run_dir(trial) / "summary.json").stat().st_mtime
                    entry["ended"] = _dt.datetime.fromtimestamp(mtime).isoformat(timespec="seconds")

    def earlier_manifest(self) -> dict[str, Any]:
        """The sweep.json an earlier invocation wrote ({} if none): one that cannot be read (over its
        size limit, not a regular file, not a JSON object) or was made with another profile or other
        overrides is exit 2 (`--dry-run` too) and left as it was, never replaced by a fresh one (it
        holds the sweep's history and its trials' records)."""
        path = self.out / MANIFEST
        if not os.path.lexists(path):
            return {}
        try:
            old = read_json_bounded(path, SWEEP_JSON_LIMIT)
            if not isinstance(old, dict):
                raise ValueError("not a JSON object")
            for key, kind in (("grid", dict), ("trials", dict), ("invocations", list)):
                if not isinstance(old.get(key, kind()), kind):
                    raise ValueError(f"its {key!r} is not a JSON {'object' if kind is dict else 'list'}")
            for name, entry in old.get("trials", {}).items():
                if not isinstance(entry, dict) or type(entry.get("launches", 0)) is not int:
                    raise ValueError(f"its record of trial {name!r} is not botorl's")
        except (OSError, ValueError) as err:
            raise BotorlError(
                f"{path} cannot be read ({err}); it records this sweep's invocations and trials, so botorl leaves it "
                f"as it was. Move it aside (e.g. `mv {path} {path}.bad`) to start its record afresh (finished trials "
                f"are found again in their run directories), or give another --out.") from None
        old_grid, grid = old.get("grid") or {}, self.grid.to_json()
        for field in ("profile", "overrides"):
            if old_grid and old_grid.get(field) != grid[field]:
                # finished trials are never rerun, so mixing settings would go unnoticed
                raise BotorlError(
                    f"{path} holds a sweep made with {field} {old_grid.get(field)!r}, but this command "
                    f"asks for {grid[field]!r}. Runs of one sweep directory share their settings (tasks, methods, "
                    "seeds and alphas may be added); use another --out or the same profile and overrides."
                )
        return old

    def _check_folders(self) -> None:
        """Every trial's run directory, where it exists, is a real folder inside --out (no link on
        the way, io.own_folder): a trial never reads or writes outside the sweep."""
        for trial in self.trials:
            own_folder(self.out, self.run_dir(trial), make=False)

    def save(self) -> None:
        self.manifest["updated"] = _now()
        states = [self.manifest["trials"][t.relpath]["state"] for t in self.trials]
        self.manifest["counts"] = {s: states.count(s) for s in sorted(set(states))}
        atomic_write_json(self.out / MANIFEST, self.manifest, root=self.out)

    def entry(self, trial: Trial) -> dict[str, Any]:
        return self.manifest["trials"][trial.relpath]

    def prepare(self, trial: Trial) -> tuple[Path, list[str], Path]:
        run_dir = self.run_dir(trial)
        stop_orphan(run_dir, self.out)
        cfg = self.config(trial)
        action, cmd = trial_command(cfg, run_dir, self.opt.command, self.out if self.opt.share_pretraining else None)
        own_folder(self.out, run_dir)
        if action == "run":
            # a stand-in command's own task has no RunConfig: it gets the fields the grid gives it
            atomic_write_json(run_dir / TRIAL_CONFIG, trial.fields if cfg is None else to_dict(cfg), exact=True,
                              root=self.out)
        log = run_dir / TRIAL_LOG
        entry = self.entry(trial)
        entry["launches"] += 1
        entry.update(state="running", action=action, started=_now(), ended=None, command=cmd, pid=None, cpu=None)
        append_text(log, f"\n===== botorl sweep: attempt {entry['launches']} ({action}) at {_now()}\n"
                         + "===== " + " ".join(cmd) + "\n", root=self.out)
        return run_dir, cmd, log

    def _finish(self, trial: Trial, returncode: int, queue: deque[Trial]) -> None:
        run_dir = self.run_dir(trial)
        entry = self.entry(trial)
        status = run_status(run_dir)
        entry.update(ended=_now(), returncode=returncode, pid=None, run_status=status)
        with contextlib.suppress(OSError):
            (run_dir / TRIAL_PID).unlink()
        if status == "finished":
            entry["state"] = "finished"
            entry.pop("error", None)
            self._tick()
            return
        entry["failures_this_invocation"] += 1
        reason = f"exited 0 but summary.json status is {status!r}" if returncode == 0 else \
            f"exited with code {returncode}"
        try:
            tail = "\n".join(read_bounded(run_dir / TRIAL_LOG, 8192, tail=True).splitlines()[-20:])
        except (OSError, ValueError):
            tail = ""
        entry["error"] = reason + "; log tail:\n" + tail
        # a BotorlError (USER_ERROR_EXIT: bad config, missing data) fails again
        retry = returncode != USER_ERROR_EXIT and entry["failures_this_invocation"] <= self.opt.max_retries
        entry["state"] = "retrying" if retry else "failed"
        if retry:
            queue.appendleft(trial)
        else:
            self._tick()
        tqdm.write(f"botorl sweep: {trial.relpath} {reason} ({'retrying' if retry else 'gave up'}; log "
                   f"{run_dir / TRIAL_LOG})", file=sys.stderr)

    def _tick(self) -> None:
        self._pbar.update(1)
        self._set_postfix()

    def _set_postfix(self) -> None:
        states = [self.entry(t)["state"] for t in self.trials]
        self._pbar.set_postfix(running=states.count("running"), failed=states.count("failed"), refresh=False)

    # SIGTERM (a scheduler's preemption) and SIGINT stop the sweep at once and are forwarded
    # to the trials, which stop at a step with a checkpoint (pipeline/preempt.py); the sweep
    # records them as interrupted and the same command resumes them. SIGKILL is handled by
    # PR_SET_PDEATHSIG and the next invocation.
    @preempt.handling()
    def run(self) -> dict[str, Any]:
        self._lock.acquire()
        running: dict[int, tuple[Trial, Any]] = {}  # by worker slot: the trial, its Popen or Ray ObjectRef
        try:
            self._check_folders()
            self._load_manifest()
            self.save()
            queue: deque[Trial] = deque(t for t in self.trials if self.entry(t)["state"] != "finished")
            done = len(self.trials) - len(queue)
            n_workers = self.backend.start(len(queue))
            self._pbar = tqdm(
                total=len(self.trials), initial=done, desc="sweep", unit="trial",
                disable=not self.opt.progress, dynamic_ncols=True,
            )
            while queue or running:
                free_slots = [s for s in range(n_workers) if s not in running]
                while queue and free_slots:
                    trial = queue.popleft()
                    slot = free_slots.pop(0)
                    running[slot] = (trial, self.backend.launch(trial, slot))
                    self.save()
                    self._set_postfix()
                finished_keys = self.backend.poll(running)
                for key, code in finished_keys:
                    self._finish(running.pop(key)[0], code, queue)
                if finished_keys:
                    self.save()
                else:
                    time.sleep(self.opt.poll_interval)
        except BaseException as err:  # a signal or an error in the sweep itself: stop the trials; they resume next time
            signum = err.signum if isinstance(err, Interrupted) else signal.SIGTERM
            if isinstance(err, Interrupted):
                err.how = err.how or "the same `botorl sweep` command (finished trials are kept, the rest resume)"
            self.backend.abort(running, signum)
            for trial, _ in running.values():
                with contextlib.suppress(Exception):
                    self.entry(trial).update(state="interrupted", ended=_now(), pid=None)
            with contextlib.suppress(Exception):
                if self.manifest:
                    self.save()
            raise
        finally:
            if self._pbar is not None:
                self._pbar.close()
                self._pbar = None
            self.backend.close()
            self._lock.release()
        return self.manifest


def check_trial_configs(sweep) -> None:
    """Build the config of each (task, method, pre-training)'s first trial, which the sweep keeps
    for it, so an unknown task, a typo in --set or a bad profile fails once, now, instead of in
    every trial."""
    for trial in [ts[0] for ts in group_by(sweep.trials, lambda t: (t.task, t.method, t.pretrain)).values()]:
        captured = io.StringIO()
        try:
            with contextlib.redirect_stderr(captured), contextlib.redirect_stdout(captured):
                cfg = sweep.config(trial)
            if cfg.wandb:  # once, now, rather than exit 2 in every trial
                require_wandb()
        except BotorlError as err:
            raise ConfigError(f"Sweep trial {trial.relpath}: {err}") from None
        except SystemExit:
            text = re.sub(r"[-─━│╭╮╰╯]{3,}|[│╭╮╰╯]", " ", captured.getvalue())  # tyro's box drawing
            tail = " ".join(text.split())[-500:]
            raise ConfigError(
                f"Sweep trial {trial.relpath}: `botorl run` rejects its settings ({tail}). Check --profile and the "
                "--set / grid overrides (dotted.path=value; `botorl run --help` lists the fields)."
            ) from None

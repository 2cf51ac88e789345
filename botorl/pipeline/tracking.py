"""Weights & Biases (``--wandb``): one W&B run per run directory (docs/running.md, "Logging",
lists the fields). A W&B that fails or does not answer within $BOTORL_WANDB_TIMEOUT seconds
is turned off with a warning, not the run.
"""

from __future__ import annotations

import hashlib
import os
import threading
from pathlib import Path

from botorl.configs.methods import get_method
from botorl.configs.schema import to_dict
from botorl.errors import ConfigError, warn

MIN_VERSION = (0, 19, 10)  # reinit="create_new": several live runs in one process (a population)
INSTALL = 'pip install "botorl[wandb]"'


def require_wandb() -> None:
    """ConfigError (exit 2) unless a wandb that can log a population is importable."""
    try:
        import wandb  # lazy: optional dependency (the wandb extra)
    except ImportError:
        raise ConfigError(f"--wandb needs the wandb package: `{INSTALL}` (or `pip install 'wandb>=0.19.10'`), "
                          f"or drop --wandb.") from None
    try:
        version = tuple(int(x) for x in str(wandb.__version__).split(".")[:3])
    except (AttributeError, ValueError):
        return  # a development build: let it try
    if version < MIN_VERSION:
        raise ConfigError(f"--wandb needs wandb >= {'.'.join(map(str, MIN_VERSION))} (one process logs every member "
                          f"of a population); this is {wandb.__version__}. `{INSTALL}` upgrades it.")


def run_id(run_root) -> str:
    """The W&B id of a run directory: its resolved path's hash, not its last name."""
    return "botorl-" + hashlib.sha256(str(Path(run_root).resolve()).encode()).hexdigest()[:20]


def _alpha(cfg):
    return cfg.alpha if cfg.alpha is not None and get_method(cfg.method).uses_alpha else None


def group(cfg) -> str:
    """``task/method[/alpha+A.AA]``: what a population or a sweep cell has in common."""
    a = _alpha(cfg)
    return f"{cfg.task}/{cfg.method}" + ("" if a is None else f"/alpha{a:+.2f}")


def name(cfg) -> str:
    a = _alpha(cfg)
    return f"{cfg.method} {cfg.task}" + ("" if a is None else f" alpha {a:+.2f}") + f" seed {cfg.seed}"


def job_type(cfg) -> str:
    stages = [s for s in get_method(cfg.method).stages if not (s == "pretrain" and cfg.pretrained is not None)]
    return "+".join(stages)


def define_metrics(wb) -> None:
    # W&B's keys: MetricsLogger logs "<stage>/<metric>" with "<stage>/step", evaluations "eval/<metric>";
    # rows on the online axis also carry "env_step"
    wb.define_metric("env_step")
    for stage in ("eval", "warmup", "finetune"):
        wb.define_metric(f"{stage}/*", step_metric="env_step")
    for stage in ("pretrain", "boto"):
        wb.define_metric(f"{stage}/step")
        wb.define_metric(f"{stage}/*", step_metric=f"{stage}/step")


def timeout() -> float:
    try:
        return float(os.environ.get("BOTORL_WANDB_TIMEOUT", "120"))
    except ValueError:
        return 120.0


def bounded(fn, seconds: float):
    """``fn()`` in a daemon thread: (True, its result) if it returned within ``seconds``, else
    (False, None) and the thread is left behind (it cannot hold the process: daemon)."""
    box: dict = {}

    def target():
        try:
            box["value"] = fn()
        except BaseException as err:  # handed to the caller
            box["error"] = err

    t = threading.Thread(target=target, name="botorl-wandb", daemon=True)
    t.start()
    t.join(seconds)
    if t.is_alive():
        return False, None
    if "error" in box:
        raise box["error"]
    return True, box.get("value")


def start(cfgs: list, runs: list) -> list:
    """One W&B run per member (``cfgs[i]``, run directory ``runs[i]``), or Nones: without
    ``--wandb``, or when W&B fails or does not answer (then once, with a warning, for all)."""
    if not cfgs or not cfgs[0].wandb:
        return [None] * len(cfgs)
    import wandb  # lazy: optional dependency (the wandb extra; run and resume call require_wandb before any work)

    limit = timeout()
    out = []
    for cfg, run in zip(cfgs, runs):
        def init(cfg=cfg, run=run):
            # W&B's files in $WANDB_DIR when the user sets it (W&B's own convention, e.g. a scratch
            # disk; each run keeps its own folder there), else in the run directory
            wb = wandb.init(project=os.environ.get("WANDB_PROJECT", "botorl"), id=run_id(run.root), name=name(cfg),
                            group=group(cfg), job_type=job_type(cfg), dir=os.environ.get("WANDB_DIR") or str(run.root),
                            config=to_dict(cfg), resume="allow", reinit="create_new")
            define_metrics(wb)
            return wb

        try:
            ok, wb = bounded(init, limit)
        except Exception as err:
            warn(f"W&B did not start ({type(err).__name__}: {err}); the run goes on without it.")
            ok, wb = True, None
        if not ok:
            warn(f"W&B did not start within {limit:g} s (no network? WANDB_MODE=offline logs "
                 f"locally); the run goes on without it.")
        if wb is None:
            finish([w for w in out if w is not None], 1)
            return [None] * len(cfgs)
        out.append(wb)
    return out


def finish(wandb_runs: list, exit_code: int = 0, seconds: float | None = None) -> None:
    """``finish`` of each W&B run, bounded in time all together (they upload what is left)."""
    wandb_runs = [w for w in wandb_runs if w is not None]
    if not wandb_runs:
        return
    limit = timeout() if seconds is None else seconds

    def all_of():
        for w in wandb_runs:
            w.finish(exit_code=exit_code)

    try:
        ok, _ = bounded(all_of, limit)
    except Exception as err:
        warn(f"W&B finish failed ({type(err).__name__}: {err}).")
        return
    if not ok:
        warn(f"W&B did not finish within {limit:g} s; its last data may not be uploaded "
             f"(`wandb sync` the run's wandb folder to send them).")

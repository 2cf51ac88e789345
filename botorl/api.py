"""botorl from Python: ``register_task``, ``run``, ``resume``, ``load_policy``, ``load_agent``, ``export_policy``.

The front door beside the command line (docs/own-task.md): ``run`` hands its arguments to the
very function ``botorl run`` calls, so a run started here is the same run, with the same run
directory. ``botorl/__init__.py`` hands these names out on first use (``import botorl`` imports
no JAX).
"""

from __future__ import annotations

import os
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

from botorl.configs.build import override_args
from botorl.data import user as data_user
from botorl.envs import registry
from botorl.envs.user import entry_of, import_entry, make_spec, probe
from botorl.errors import BotorlError, ConfigError, warn
from botorl.pipeline.export import export_policy
from botorl.pipeline.policy import load_agent, load_policy
from botorl.pipeline.rundir import POPULATION_FILE, read_json


def register_task(name: str, make_env: Callable[[int], Any] | str, dataset, max_episode_steps: int,
                  success_key: str | None = "success", domain: str | None = None, reward_scale: float = 1.0,
                  reward_bias: float = 0.0, ref_min_score: float | None = None, ref_max_score: float | None = None):
    """Register a task of your own for this process; returns its ``TaskSpec`` (docs/own-task.md).

    ``make_env(seed)`` (or ``"MODULE:FUNCTION"``) returns a Gymnasium env with a ``Box`` action
    space and a ``Box`` or ``Dict`` observation space. ``dataset``: a dict of arrays, a path or a
    botorl ``Dataset``, actions in the env's own units. ``success_key``: the info key read as
    success (None or absent: success is off). ``domain``: a paper domain whose presets the task
    takes. Training's rewards are ``reward_scale * r + reward_bias``. A task without success is
    reported in its episode return, or with ``ref_min_score`` and ``ref_max_score`` (the returns of
    a poor and a good policy) in the normalised score ``100 * (R - min) / (max - min)``. Bad input
    raises ``BotorlError``; registering a name again replaces it.
    """
    if isinstance(make_env, str):
        entry = make_env
        make_env, path = import_entry(entry)
    elif callable(make_env):
        entry, path = entry_of(make_env)
    else:
        raise ConfigError(f"task {name!r}: make_env is a {type(make_env).__name__}; give a function make_env(seed) "
                          f"returning a Gymnasium env, or its 'MODULE:FUNCTION'.")
    task = probe(make_env, max_episode_steps, success_key, name=name,
                 key_given=success_key not in (None, "success"))
    task = replace(task, entry=entry, path=path)
    ref, ds = data_user.to_dataset(dataset, task, name=name, max_episode_steps=max_episode_steps)
    spec = make_spec(name, make_env, task, max_episode_steps=max_episode_steps, domain=domain,
                     reward_scale=reward_scale, reward_bias=reward_bias, data_ref=ref, ref_min_score=ref_min_score,
                     ref_max_score=ref_max_score)
    registry.register(spec)
    data_user.hold(name, ref, ds)
    if task.success_off and success_key is not None:
        warn(f"task {name!r}: {task.success_off}.")
    return spec


def _call(main, argv: list[str]) -> int:
    """A command's main from Python: its usage errors (tyro/argparse exit) become a ConfigError."""
    try:
        return main(argv)
    except SystemExit as err:
        if err.code in (0, None):
            return 0
        raise ConfigError(f"botorl refused the arguments {' '.join(argv)} (the message above says which); check "
                          f"the override names against `botorl run --help`.") from None


def run(task: str | Any = "pointmaze-umaze", method: str = "boto", profile: str = "quick", out: str | os.PathLike | None = None,
        seeds=None, **overrides) -> dict[str, Any]:
    """Run ``method`` on ``task`` as ``botorl run`` does (the same function, the same run directory);
    returns the run's summary (summary.json as a dict; ``status`` "finished" when it ran through).

    ``task``: a task name (botorl's, or one given to ``register_task``) or the TaskSpec it returned.
    ``out``: the run directory (default ``runs/<task>-<method>-<time>``). ``seeds``: several seeds
    (a list, or "0-7") run as one population: the summary then has ``members`` (each member's
    summary) and ``run_dir``. ``overrides``: any config field, dotted as on the command line, as
    ``online__steps=50_000`` or a dict (``online={"steps": 50_000}``, ``**{"online.steps": 50_000}``).
    """
    # lazy: JAX; `import botorl` hands out this module's names without it (tests/test_own_task.py)
    from botorl.pipeline.cli import run_main

    name = getattr(task, "name", task)
    if not isinstance(name, str):
        raise ConfigError(f"task = {task!r}: give a task name or the TaskSpec register_task returned.")
    out = Path("runs") / f"{name}-{method}-{time.strftime('%Y%m%d-%H%M%S')}" if out is None else Path(out)
    argv = ["--task", name, "--method", method, "--profile", profile, "--out", str(out)]
    if seeds is not None:
        if isinstance(seeds, int) and not isinstance(seeds, bool):
            argv += ["--seed", str(seeds)]
        else:
            argv += ["--seeds", seeds if isinstance(seeds, str) else ",".join(str(int(s)) for s in seeds)]
    argv += override_args(overrides)
    _call(run_main, argv)
    return _summary(out)


def resume(run_dir: str | os.PathLike, *, checkpoint: str | None = None, progress: bool = True,
           allow_pickle: bool = False, env: str | None = None) -> dict[str, Any]:
    """``botorl resume RUN_DIR [--from CHECKPOINT] [--no-progress] [--allow-pickle] [--env MODULE:FUNCTION]``
    from Python; returns the summary as ``run`` does. A task of one's own must be registered again
    in this process first (the same ``register_task`` call), or its entry point given again as
    ``env`` (the one the run recorded): botorl never imports what a run directory's files name."""
    from botorl.pipeline.cli import resume_main  # lazy: JAX, as in ``run``

    root = Path(run_dir)
    argv = [str(root)] + (["--from", checkpoint] if checkpoint else []) + ([] if progress else ["--no-progress"]) + \
        (["--allow-pickle"] if allow_pickle else []) + (["--env", str(env)] if env is not None else [])
    _call(resume_main, argv)
    return _summary(root)


def _summary(root: Path) -> dict[str, Any]:
    if not (root / POPULATION_FILE).exists():
        return read_json(root / "summary.json")
    data = read_json(root / POPULATION_FILE)
    members = [read_json(root / m["name"] / "summary.json") for m in data.get("members", [])]
    return {"status": data.get("status"), "run_dir": str(root), "members": members}


__all__ = ["BotorlError", "register_task", "run", "resume", "load_policy", "load_agent", "export_policy",
           "override_args"]

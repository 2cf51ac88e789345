"""A task of the user's own in a run's config (docs/own-task.md): registered from ``botorl run --env
MODULE:FUNCTION ...`` (``expand_argv``), again when a run directory is read back (``register_given``),
and checked by ``validate`` (``ensure_task``).

A run directory is data (docs/reliability.md): the entry point and folder its config.json
records are never imported, called or put on ``sys.path``; only an entry the user typed (checked
equal to the recorded one) or a ``botorl.register_task`` of the calling process makes the env.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from botorl.envs import registry
from botorl.envs.user import import_entry, make_spec, probe, split_entry
from botorl.errors import ConfigError

# the command line's flags of a task of one's own
FLAGS = ("--env", "--env-max-steps", "--success-key", "--env-domain", "--env-reward-scale", "--env-reward-bias",
         "--ref-min-score", "--ref-max-score")


def _pull(argv: list[str], flags) -> tuple[dict[str, str], list[str]]:
    """``flags`` (``--x V`` or ``--x=V``) out of argv; each may be given once."""
    found: dict[str, str] = {}
    rest: list[str] = []
    i = 0
    while i < len(argv):
        key, eq, val = argv[i].partition("=")
        if key in flags:
            if not eq:
                if i + 1 >= len(argv):
                    raise ConfigError(f"{key} needs a value.")
                val = argv[i + 1]
                i += 1
            if key in found:
                raise ConfigError(f"{key} is given twice ({found[key]!r} and {val!r}); give it once.")
            found[key] = val
        else:
            rest.append(argv[i])
        i += 1
    return found, rest


def _number(flag: str, text: str, kind):
    try:
        return kind(text)
    except ValueError:
        raise ConfigError(f"{flag} {text!r}: give a{'n integer' if kind is int else ' number'}.") from None


def _optional(flag: str, found: dict[str, str]) -> float | None:
    return _number(flag, found[flag], float) if flag in found else None


def expand_argv(argv: list[str]) -> list[str]:
    """``botorl run``'s arguments with a task of one's own registered and named by ``--task``
    (unchanged when there is no ``--env``)."""
    found, rest = _pull(list(argv), FLAGS)
    if not found:
        return list(argv)
    if "--env" not in found:
        raise ConfigError(f"{', '.join(found)} describe a task of your own, which --env MODULE:FUNCTION names "
                          f"(e.g. --env mytask:make_env --data.path logged.npz --env-max-steps 50).")
    if "--env-max-steps" not in found:
        raise ConfigError(f"--env {found['--env']} needs --env-max-steps N: the episode length limit of your env.")
    given, rest = _pull(rest, ("--data.path", "--task"))
    if "--data.path" not in given:
        raise ConfigError(f"--env {found['--env']} needs --data.path FILE: your logged transitions (a .npz with "
                          f"observations, actions, rewards, next_observations, terminals; a D4RL .hdf5; a Minari "
                          f"dataset folder or id).")
    data = given["--data.path"]
    if Path(data).expanduser().exists():
        data = str(Path(data).expanduser().resolve())  # resume may run from another folder
    entry = found["--env"]
    module, func = split_entry(entry)
    name = given.get("--task") or f"{module}.{func}"
    register_entry(name, entry, data, _number("--env-max-steps", found["--env-max-steps"], int),
                   success_key=found.get("--success-key", "success"), key_given="--success-key" in found,
                   domain=found.get("--env-domain"),
                   reward_scale=_number("--env-reward-scale", found.get("--env-reward-scale", "1"), float),
                   reward_bias=_number("--env-reward-bias", found.get("--env-reward-bias", "0"), float),
                   ref_min_score=_optional("--ref-min-score", found), ref_max_score=_optional("--ref-max-score", found))
    return rest + ["--task", name, "--data.path", data]


def register_entry(name: str, entry: str, data: str, max_steps: int, *, success_key: str | None = "success",
                   key_given: bool = False, domain: str | None = None, reward_scale: float = 1.0,
                   reward_bias: float = 0.0, ref_min_score: float | None = None, ref_max_score: float | None = None):
    """Import ``entry`` (one the user gave, never one a file names), look at its env and register
    the task ``name`` reading ``data`` (the file is read when the run loads its data). Returns the
    TaskSpec."""
    make_env, found = import_entry(entry)
    task = probe(make_env, max_steps, success_key, name=name, key_given=key_given)
    task = replace(task, entry=entry, path=found)
    return registry.register(make_spec(name, make_env, task, max_episode_steps=max_steps, domain=domain,
                                       reward_scale=reward_scale, reward_bias=reward_bias, data_ref=data,
                                       ref_min_score=ref_min_score, ref_max_score=ref_max_score))


def register_given(cfg, entry: str | None) -> None:
    """Register a run's own task from ``entry``, the ``--env MODULE:FUNCTION`` the user gave again
    (None: nothing to do). It must be the entry the run recorded: the user says which code runs,
    the run directory only which code it expects."""
    if entry is None:
        return
    e = cfg.env
    if e.max_steps is None:
        raise ConfigError(f"--env {entry}: this run's task {cfg.task!r} is one of botorl's, not a task of your own; "
                          f"drop --env.")
    if e.entry is None or str(entry) != e.entry:
        raise ConfigError(f"--env {entry}: this run was trained on the entry point {e.entry!r} (its config.json "
                          f"says); give that one, or start a new run with `botorl run --env {entry} ...`.")
    if registry.is_registered(cfg.task):
        return  # botorl.register_task in this process already made it; ensure_task compares the envs
    if not cfg.data.path:
        raise ConfigError(f"task {cfg.task!r}: its data were given in memory to botorl.register_task; register the "
                          f"task again in this process (then botorl.resume(DIR)), or register a data file instead.")
    register_entry(cfg.task, entry, cfg.data.path, e.max_steps, success_key=e.success_key, domain=e.domain,
                   reward_scale=e.reward_scale, reward_bias=e.reward_bias,
                   ref_min_score=cfg.metric.ref_min_score, ref_max_score=cfg.metric.ref_max_score)


def ensure_task(cfg) -> None:
    """A ConfigError unless a run's task of one's own is registered in this process (by
    ``register_given`` from the user's ``--env``, or by ``botorl.register_task``) with the env the
    run was trained on. Nothing a file names is imported here."""
    e = cfg.env
    if e.max_steps is None:
        return  # one of botorl's tasks
    if not registry.is_registered(cfg.task):
        if e.entry is None:
            how = (f"register it again in this process with botorl.register_task({cfg.task!r}, make_env, ...) (the "
                   f"script that trained it does), then call botorl from that process")
        else:
            how = (f"give its entry point again with --env {e.entry} (`botorl resume DIR --env {e.entry}`; eval, "
                   f"export and run --config take it too; run from the folder holding its module, or with that "
                   f"folder on PYTHONPATH), or register it in this process with botorl.register_task({cfg.task!r}, ...)")
        raise ConfigError(f"task {cfg.task!r} is a task of your own, and botorl does not import or call code a run "
                          f"directory names (its config.json is data); {how}.")
    u = registry.get_task(cfg.task).user
    if u is None:
        return
    fields = {"observation width": "obs_dim", "action width": "action_dim", "action low": "action_low",
              "action high": "action_high", "dict observation keys": "obs_keys"}
    changed = [f"{k} {getattr(e, f)} -> {getattr(u, f)}" for k, f in fields.items()
               if getattr(e, f) is not None and _as_tuple(getattr(e, f)) != _as_tuple(getattr(u, f))]
    if changed:
        raise ConfigError(f"task {cfg.task!r}: the env is not the one this run was trained on ({'; '.join(changed)}). "
                          f"Restore the env (entry {e.entry or 'registered from Python'}) or start a new run.")


def _as_tuple(v):
    return tuple(v) if isinstance(v, (list, tuple)) else v

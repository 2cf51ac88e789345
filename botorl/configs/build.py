"""Preset + command line -> a resolved, validated ``RunConfig`` (``botorl run``'s arguments):
--task, --method, --profile and --pretrain pick the preset, tyro parses every argument over it,
then ``resolve`` and ``validate``. ``make_config`` makes the same config from field values (a
sweep's trials); ``--config FILE`` reads back one it wrote.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import typing
from collections.abc import Mapping
from dataclasses import replace
from typing import Any

import tyro

from botorl.configs.custom import expand_argv, register_given
from botorl.configs.methods import resolve_pretrain
from botorl.errors import ConfigError
from botorl.io import read_json_bounded
from botorl.jaxsetup import check_precision

_SHORTCUTS = {"--demos": "--data.demos", "--dataset": "--data.path"}
_LIST_FLAGS = ("--seeds", "--alphas")


def _expand_shortcuts(argv: list[str]) -> list[str]:
    out = []
    for a in argv:
        key, eq, val = a.partition("=")
        if key in _SHORTCUTS:
            out.append(_SHORTCUTS[key] + (eq + val if eq else ""))
        elif out and out[-1] in _LIST_FLAGS and not eq:
            out[-1] += "=" + a  # --alphas -1:1:0.5: a value with a leading '-' is no flag to tyro
        else:
            out.append(a)
    for flag in _LIST_FLAGS:
        given = [a.partition("=")[2] for a in out if a.partition("=")[0] == flag]
        if flag in out:
            raise ConfigError(f"{flag} needs a value, e.g. {flag} 0-7.")
        if len(given) > 1:
            raise ConfigError(f"{flag} is given twice ({given[0]!r} and {given[1]!r}); give it once.")
    return out


_AGENT_PREFIXES = ("--offline.cql.", "--offline.iql.", "--online.sac.")


def _refuse_derived(argv: list[str]) -> None:
    """A flag of a field ``resolve`` derives (``configs.resolve.DERIVED``) would be overwritten
    unseen: refuse it, naming the one flag that sets the fact."""
    from botorl.configs.resolve import DERIVED  # lazy: JAX, as in build_config

    for a in argv:
        key = a.partition("=")[0]
        prefix = next((p for p in _AGENT_PREFIXES if key.startswith(p)), None)
        if prefix is None:
            continue
        name = key[len(prefix):].replace("-", "_")
        name = name[3:] if name.startswith("no_") else name
        # utd_ratio: the agents' copy of the UTD until the update's batch carried it
        src = DERIVED.get(name, "online.utd" if name == "utd_ratio" else None)
        if src is not None:
            src = "--" + src.replace("_", "-")
            raise ConfigError(f"{key}: every agent takes this from {src}, the one field that holds it (pre-training "
                              f"and fine-tuning alike); give {src} instead.")


def _pre_parse(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(add_help=False)
    for flag, default in (("--task", "pointmaze-umaze"), ("--method", "boto"), ("--profile", "quick"),
                          ("--pretrain", None), ("--precision", "tf32")):
        p.add_argument(flag, default=default)
    ns, _ = p.parse_known_args(argv)
    if ns.pretrain in ("None", "none"):
        ns.pretrain = None
    return ns


def make_config(overrides: Mapping | None = None, **fields: Any):
    """The config of `botorl run` with ``fields`` (None: the preset's) and then ``overrides``
    ({dotted.path: value}), each value made the flag that sets it, so every config is made the
    one way, with `botorl run`'s checks."""
    given = {k: v for k, v in fields.items() if v is not None}
    return build_config(override_args(given) + override_args(overrides or {}))


def build_config(argv: list[str]):
    """Preset + command line -> resolved, validated RunConfig (ConfigError on bad input)."""
    if _given(argv, "--config"):
        return _load_config(argv)
    # lazy: JAX (the agents' configs in the schema); botorl.api imports this module
    from botorl.configs import presets, resolve, schema

    argv = _expand_shortcuts(list(argv))
    argv = expand_argv(argv)  # --env MODULE:FUNCTION: a task of one's own, registered here (configs/custom.py)
    _refuse_derived(argv)
    pre = _pre_parse(argv)
    resolve_pretrain(pre.method, pre.pretrain)  # the method too: clear errors before tyro's generic ones
    check_precision(pre.precision)
    default = presets.make_preset(pre.task, pre.profile, pre.method, pre.pretrain)
    cfg = tyro.cli(
        schema.RunConfig,
        default=default,
        args=argv,
        prog="botorl run",
        description="Run one method on one task, offline to online (preset: "
        f"task={pre.task}, method={pre.method}, profile={pre.profile}). "
        "Many runs as one program (a population): --seeds 0-7 (or 0,2,5) for several seeds, and for "
        "--method boto --alphas -1:1:0.5 (or -1,0,1) for several alphas, each member its own run "
        "directory under --out; --pretrained DIR starts every member from the finished pre-training "
        "of the same seed and settings under DIR. A task of your own: --env MODULE:FUNCTION --data.path FILE "
        "--env-max-steps N [--success-key K] (the docs' Your own task page). --config FILE [--out DIR] runs "
        "the config `botorl sweep` wrote for a trial. --print-config prints the resolved config as JSON and "
        "exits, writing nothing.",
    )
    for one, example in (("seed", "0-7"), ("alpha", "-1:1:0.25")):  # a member's flag beside the population's
        if getattr(cfg, f"{one}s") is not None and _given(argv, f"--{one}"):
            raise ConfigError(f"--{one} and --{one}s are both given; a population takes --{one}s (e.g. --{one}s {example}) only.")
    cfg = resolve.resolve(cfg)
    resolve.validate(cfg)
    return cfg


def _given(argv: list[str], flag: str) -> bool:
    return any(a.split("=", 1)[0] == flag for a in argv)


def _is_flag(key: str) -> bool:
    """Whether ``key`` (a dotted path) is a plain bool field, which tyro makes a flag pair
    (``bool | None`` fields take a value)."""
    from botorl.configs.schema import RunConfig  # lazy: JAX, as in build_config

    cls = RunConfig
    for part in key.replace("-", "_").split("."):
        if not dataclasses.is_dataclass(cls):
            return False
        hints = typing.get_type_hints(cls)
        if part not in hints:
            return False
        cls = hints[part]
    return cls is bool


def flat_overrides(overrides: Mapping) -> dict[str, Any]:
    """``flatten``, where ``network__layer_norm`` also means ``network.layer_norm``."""
    from botorl.configs.schema import flatten  # lazy: JAX, as in build_config

    return {k.replace("__", "."): v for k, v in flatten(overrides).items()}


def override_args(overrides: Mapping) -> list[str]:
    """``{"online.steps": 5000, "network": {"layer_norm": False}}`` -> ``--online.steps 5000
    --network.no-layer-norm``; a value may be the command line's text too ("False", "-0.5")."""
    argv: list[str] = []
    for key, v in flat_overrides(overrides).items():
        text = "None" if v is None else str(v)
        if text.lower() in ("true", "false") and _is_flag(key):  # tyro's flags: --x / --no-x (--a.b.no-x nested)
            head, _, last = key.rpartition(".")
            argv.append(f"--{key}" if text.lower() == "true" else f"--{head + '.' if head else ''}no-{last.replace('_', '-')}")
        elif isinstance(v, (list, tuple)):
            argv += [f"--{key}", *map(str, v)]
        else:
            argv += [f"--{key}={text}"] if text.startswith("-") else [f"--{key}", text]  # "=": a leading '-' is no flag
    return argv


def _load_config(argv: list[str]):
    """The config in FILE as `botorl sweep` wrote it, with the run's own --out, --pretrained and
    --no-progress; validated again."""
    from botorl.configs import resolve, schema  # lazy: JAX, as in build_config

    p = argparse.ArgumentParser(prog="botorl run", add_help=False, allow_abbrev=False)
    for flag in ("--config", "--out", "--pretrained", "--env"):
        p.add_argument(flag)
    p.add_argument("--no-progress", action="store_true")
    ns, rest = p.parse_known_args(argv)
    if rest:
        others = [a.split("=", 1)[0] for a in rest if a.startswith("-")] or rest
        raise ConfigError(f"--config {ns.config} holds the whole config; {', '.join(others)} cannot go with it (only "
                          f"--out, --pretrained, --env and --no-progress can). Drop them, or give the flags without --config.")
    try:
        data = read_json_bounded(ns.config)
        if isinstance(data, dict):
            # a file written before the field: its runs computed at JAX's default, which is tf32
            data.setdefault("precision", "tf32")
            # a file from before the agents' configs lost their copy of the UTD: online.utd holds it
            for outer, inner in (("online", "sac"), ("offline", "cql")):
                section = data.get(outer)
                if isinstance(section, dict) and isinstance(section.get(inner), dict):
                    section[inner].pop("utd_ratio", None)
        cfg = schema.from_dict(schema.RunConfig, data)
        if json.dumps(schema.to_dict(cfg), sort_keys=True) != json.dumps(data, sort_keys=True):  # missing, unknown, mistyped
            raise ValueError("not every field of a run config, as botorl writes it")
    except (OSError, TypeError, ValueError, KeyError, AttributeError) as err:
        raise ConfigError(f"--config {ns.config} cannot be read as a run config ({err}); give a file botorl wrote "
                          f"(`botorl sweep` writes one per trial).") from None
    cfg = replace(cfg, out=ns.out or cfg.out, pretrained=ns.pretrained or cfg.pretrained,
                  progress=cfg.progress and not ns.no_progress)
    resolve.check_bounds(cfg)
    register_given(cfg, ns.env)  # a task of one's own: only from the user's --env, never from the file
    resolve.validate(cfg)
    return cfg

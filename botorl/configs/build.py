"""Preset + command line -> a resolved, validated ``RunConfig`` (``botorl run``'s arguments).

``build_config`` first reads --task, --method, --profile and --pretrain to pick the preset
(botorl/configs/presets.py), then tyro parses every argument over it, so any field of the
config can be set as ``--<dotted.path> VALUE``; ``resolve`` and ``validate`` follow, so a bad
configuration is a ConfigError before any work.
"""

from __future__ import annotations

import argparse

from botorl.errors import ConfigError

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
    from botorl.configs.resolve import DERIVED

    for a in argv:
        key = a.partition("=")[0]
        prefix = next((p for p in _AGENT_PREFIXES if key.startswith(p)), None)
        if prefix is None:
            continue
        name = key[len(prefix):].replace("-", "_")
        name = name[3:] if name.startswith("no_") else name
        if name in DERIVED:
            src = "--" + DERIVED[name].replace("_", "-")
            raise ConfigError(f"{key}: every agent takes this from {src}, the one field that holds it (pre-training "
                              f"and fine-tuning alike); give {src} instead.")


def _pre_parse(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--task", default="pointmaze-umaze")
    p.add_argument("--method", default="boto")
    p.add_argument("--profile", default="quick")
    p.add_argument("--pretrain", default=None)
    ns, _ = p.parse_known_args(argv)
    if ns.pretrain in ("None", "none"):
        ns.pretrain = None
    return ns


def build_config(argv: list[str]):
    """Preset + command line -> resolved, validated RunConfig (ConfigError on bad input)."""
    import tyro

    from botorl.configs.custom import expand_argv
    from botorl.configs.methods import get_method, resolve_pretrain
    from botorl.configs.presets import make_preset
    from botorl.configs.resolve import resolve, validate
    from botorl.configs.schema import RunConfig
    from botorl.envs.registry import get_task

    argv = _expand_shortcuts(list(argv))
    argv = expand_argv(argv)  # --env MODULE:FUNCTION: a task of one's own, registered here (configs/custom.py)
    _refuse_derived(argv)
    pre = _pre_parse(argv)
    get_method(pre.method)  # clear errors before tyro's generic ones
    resolve_pretrain(pre.method, pre.pretrain)
    get_task(pre.task)
    default = make_preset(pre.task, pre.profile, pre.method, pre.pretrain)
    cfg = tyro.cli(
        RunConfig,
        default=default,
        args=argv,
        prog="botorl run",
        description="Run one method on one task, offline to online (preset: "
        f"task={pre.task}, method={pre.method}, profile={pre.profile}). "
        "Many runs as one program (a population): --seeds 0-7 (or 0,2,5) for several seeds, and for "
        "--method boto --alphas -1:1:0.5 (or -1,0,1) for several alphas, each member its own run "
        "directory under --out; --pretrained DIR starts every member from the finished pre-training "
        "of the same seed and settings under DIR. A task of your own: --env MODULE:FUNCTION --data.path FILE "
        "--env-max-steps N [--success-key K] (the docs' Your own task page).",
    )
    _check_population_flags(argv, cfg)
    cfg = resolve(cfg)
    validate(cfg)
    return cfg


# ------------------------------------------------------------------ a population's command line
def _given(argv: list[str], flag: str) -> bool:
    return any(a.split("=", 1)[0] == flag for a in argv)


def _check_population_flags(argv: list[str], cfg) -> None:
    if cfg.seeds is not None and _given(argv, "--seed"):
        raise ConfigError("--seed and --seeds are both given; a population takes --seeds (e.g. --seeds 0-7) only.")
    if cfg.alphas is not None and _given(argv, "--alpha"):
        raise ConfigError("--alpha and --alphas are both given; a population takes --alphas (e.g. --alphas -1:1:0.25) only.")

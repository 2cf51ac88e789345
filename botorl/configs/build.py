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


def _expand_shortcuts(argv: list[str]) -> list[str]:
    out = []
    for a in argv:
        key, eq, val = a.partition("=")
        if key in _SHORTCUTS:
            out.append(_SHORTCUTS[key] + (eq + val if eq else ""))
        else:
            out.append(a)
    return out


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
        "--env-max-steps N [--success-key K] (docs/own-task.md).",
    )
    cfg = resolve(cfg)
    validate(cfg)
    return cfg


# ------------------------------------------------------------------ a population's command line
POPULATION_FLAGS = ("--seeds", "--alphas")


def is_population(argv: list[str]) -> bool:
    return any(a.split("=", 1)[0] in POPULATION_FLAGS for a in argv)


def split_population_args(argv: list[str]) -> tuple[dict[str, str], list[str]]:
    """--seeds/--alphas (``--x V`` or ``--x=V``) out of argv; each may be given once."""
    found: dict[str, str] = {}
    rest: list[str] = []
    i = 0
    while i < len(argv):
        a = argv[i]
        key, eq, val = a.partition("=")
        if key in POPULATION_FLAGS:
            if not eq:
                if i + 1 >= len(argv):
                    raise ConfigError(f"{key} needs a value, e.g. {key} 0-7.")
                val = argv[i + 1]
                i += 1
            if key in found:
                raise ConfigError(f"{key} is given twice ({found[key]!r} and {val!r}); give it once.")
            found[key] = val
        else:
            rest.append(a)
        i += 1
    return found, rest


def _given(rest: list[str], flag: str) -> bool:
    return any(a.split("=", 1)[0] == flag for a in rest)


def build_population(argv: list[str]):
    """(shared config, member configs, Member list) from a `botorl run` command line."""
    from botorl.configs.members import make_members, member_config, parse_alphas, parse_seeds
    from botorl.configs.methods import get_method

    found, rest = split_population_args(list(argv))
    if "--seeds" in found and _given(rest, "--seed"):
        raise ConfigError("--seed and --seeds are both given; a population takes --seeds (e.g. --seeds 0-7) only.")
    if "--alphas" in found and _given(rest, "--alpha"):
        raise ConfigError("--alpha and --alphas are both given; a population takes --alphas (e.g. --alphas -1:1:0.25) only.")
    seeds = parse_seeds(found["--seeds"]) if "--seeds" in found else None
    alphas = parse_alphas(found["--alphas"]) if "--alphas" in found else None
    extra = []
    if seeds is None:
        cfg0 = build_config(rest)
        seeds = [cfg0.seed]
    else:
        extra += ["--seed", str(seeds[0])]
    if alphas is not None:
        extra.append(f"--alpha={alphas[0]}")
    cfg = build_config(rest + extra)  # validates everything shared, and the first member's alpha
    uses_alpha = get_method(cfg.method).uses_alpha
    if alphas is not None and not uses_alpha:
        raise ConfigError(f"--alphas sets BOTO's bias controller; --method {cfg.method} has no BOTO phase. "
                          f"Drop --alphas, or use --method boto.")
    members = make_members(seeds, alphas or [None], uses_alpha)
    return cfg, members, [member_config(cfg, m.seed, m.alpha) for m in members]

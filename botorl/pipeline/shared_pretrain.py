"""Start from pre-training that another run already did (``--pretrained DIR``; docs/populations.md).

Each member takes the finished pre-training under ``DIR`` whose *fingerprint* (the settings
that decide the pre-trained numbers; checkpoint spacing among them, as it cuts the update
chunks) equals its own; without one, an error names the closest and how it differs.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from botorl.agents import agent_file
from botorl.agents.population import stack
from botorl.configs.schema import RunConfig, from_dict, to_dict
from botorl.errors import ConfigError, warn
from botorl.io import atomic_write_bytes, read_bounded_bytes
from botorl.pipeline.rundir import LOG_LIMIT, read_json
from botorl.pipeline.stages import make_pretrain_agent

PRETRAIN_FINAL = "pretrain-final"


def fingerprint_of(d: dict[str, Any]) -> dict[str, Any]:
    """The settings that decide a member's pre-trained agent, of a config as ``to_dict`` writes it."""
    offline = {k: v for k, v in d["offline"].items() if k != "log_every"}  # changes what is logged, not learned
    return {"task": d["task"], "seed": d["seed"], "pretrain": d["pretrain"], "data": d["data"],
            "network": d["network"], "offline": offline, "checkpoint_every": d["checkpoint_every"]}


def _key(fp: dict) -> str:
    return json.dumps(fp, sort_keys=True, default=str)


def _first_difference(a: Any, b: Any, path: str = "") -> str | None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            d = _first_difference(a.get(k), b.get(k), f"{path}.{k}" if path else k)
            if d is not None:
                return d
        return None
    return None if a == b else f"{path} ({b!r} there, {a!r} here)"


def candidates(directory: str | Path) -> list[tuple[Path, dict]]:
    """(run directory, its fingerprint) for every run under ``directory`` with a finished pre-training."""
    root = Path(directory).expanduser()
    if not root.is_dir():
        raise ConfigError(f"--pretrained {directory}: no such directory. Point it at a run, population or sweep "
                          f"directory whose pre-training has finished.")
    found = []
    for config in sorted(root.rglob("config.json")):
        run = config.parent
        if ("checkpoints" in run.relative_to(root).parts
                or not (run / "checkpoints" / PRETRAIN_FINAL / "agent.ckpt").is_file()):
            continue
        try:
            cfg = from_dict(RunConfig, read_json(config))
        except (OSError, ValueError, TypeError):
            continue
        found.append((run, fingerprint_of(to_dict(cfg))))
    return found


def match(member_cfgs, directory: str | Path, *, strict: bool = True) -> list[Path] | None:
    """The run directory each member takes its pre-training from; with ``strict=False`` None
    when any member has no match (the caller then pre-trains), else a ConfigError naming the
    closest candidate and how it differs."""
    found = candidates(directory)
    index = {_key(fp): run for run, fp in found}
    out = []
    for cfg in member_cfgs:
        fp = fingerprint_of(to_dict(cfg))
        run = index.get(_key(fp))
        if run is None:
            if not strict:
                return None
            same_seed = [(r, f) for r, f in found if f["seed"] == fp["seed"] and f["task"] == fp["task"]]
            if not same_seed:
                raise ConfigError(
                    f"--pretrained {directory}: no finished pre-training of {fp['task']} at seed {fp['seed']} "
                    f"there ({len(found)} finished pre-trainings found). Pre-train that seed (drop --pretrained) or "
                    f"point --pretrained at the runs that did.")
            r, f = same_seed[0]
            raise ConfigError(
                f"--pretrained {directory}: {r} pre-trained seed {fp['seed']} with other settings: "
                f"{_first_difference(fp, f)}. Use the same pre-training settings, or drop --pretrained.")
        out.append(run)
    return out


def load(ctx, sources: list[Path]):
    """The members' pre-trained agents (stacked), with each source's pre-training logs copied
    into the member's run directory so its metrics read as if it had pre-trained itself."""
    d = ctx.d_offline
    agents = []
    for src, member in zip(sources, ctx.members):
        like = make_pretrain_agent(member.cfg, d.obs_dim, d.action_dim, member.cfg.seed)
        agents.append(agent_file.load(str(src / "checkpoints" / PRETRAIN_FINAL / "agent.ckpt"), like=like))
        for name in ("pretrain.csv", "pretrain.jsonl"):
            if (src / "metrics" / name).is_file() and src.resolve() != member.run.root.resolve():
                try:
                    atomic_write_bytes(member.run.metrics / name, read_bounded_bytes(src / "metrics" / name, LOG_LIMIT),
                                       root=member.run.root)
                except ValueError as err:  # not a regular file, or a huge one: the logs only, not the run
                    warn(f"{src / 'metrics' / name} not copied ({err}).")
    return stack(agents)

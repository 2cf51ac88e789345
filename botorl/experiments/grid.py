"""The grid of a sweep: tasks x methods x seeds (x alphas, BOTO only: the other methods get one
trial per seed with alpha null), each trial's deterministic run-directory name (so the same
command again finds the trials the first one made) and the config each runs.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
from pathlib import Path
from typing import Any

import yaml

from botorl.configs import members
from botorl.configs.build import flat_overrides, make_config
from botorl.configs.members import Member, parse_alphas
from botorl.configs.methods import METHODS, PRETRAIN_ALGOS
from botorl.errors import ConfigError
from botorl.experiments.runs import group_by
from botorl.io import read_bounded


@dataclasses.dataclass(frozen=True)
class Trial:
    """One run of the grid: its config's fields and its run directory."""

    task: str
    method: str
    seed: int
    alpha: float | None = None  # BOTO only; None = the task's preset alpha
    pretrain: str | None = None  # BOTO only; None = the pipeline's default pre-training

    @property
    def relpath(self) -> str:
        """`<task>/<method>[-<pretrain>]/[alpha<+0.50>/]seed<k>`."""
        label = method_label(self.method, self.pretrain)
        if self.method != "boto":
            return f"{self.task}/{label}/seed{self.seed}"
        a = self.alpha
        alpha = "alpha_preset" if a is None else f"alpha{a:+.2f}" if round(a, 2) == round(a, 6) else f"alpha{a:+.6f}"
        return f"{self.task}/{label}/{alpha}/seed{self.seed}"

    @property
    def fields(self) -> dict[str, Any]:
        """The fields of its RunConfig it sets (None: the preset's)."""
        return {"task": self.task, "method": self.method, "pretrain": self.pretrain, "alpha": self.alpha,
                "seed": self.seed}

    def to_json(self) -> dict[str, Any]:
        return self.fields


@dataclasses.dataclass(frozen=True)
class PopulationJob:
    """Trials of one (task, method, pre-training) trained as one population, the product of
    ``seeds`` and ``alphas`` (one `botorl run` of a config with those): the unit of work of
    `botorl sweep --population-size K`. A member's run directory is ``<relpath>/<Member.name>``."""

    task: str
    method: str
    pretrain: str | None
    seeds: tuple[int, ...]
    alphas: tuple[float | None, ...] = (None,)

    @property
    def trials(self) -> list[Trial]:
        return [Trial(self.task, self.method, s, a, self.pretrain) for a in self.alphas for s in self.seeds]

    @property
    def relpath(self) -> str:
        """`<task>/<method>[-<pretrain>]/pop-<members>m-<hash>`: the same members, the same name."""
        key = json.dumps([list(self.seeds), [None if a is None else round(a, 6) for a in self.alphas]])
        digest = hashlib.sha1(key.encode()).hexdigest()[:8]
        return f"{self.task}/{method_label(self.method, self.pretrain)}/pop-{len(self.seeds) * len(self.alphas)}m-{digest}"

    def member_dir(self, trial: Trial) -> str:
        """A member's run directory, relative to the sweep directory."""
        return f"{self.relpath}/{Member(trial.seed, trial.alpha).name}"

    @property
    def fields(self) -> dict[str, Any]:
        alphas = ",".join(format_alpha(a) for a in self.alphas) if any(a is not None for a in self.alphas) else None
        return {"task": self.task, "method": self.method, "seeds": ",".join(str(s) for s in self.seeds),
                "alphas": alphas, "pretrain": self.pretrain}

    def to_json(self) -> dict[str, Any]:
        return {"task": self.task, "method": self.method, "pretrain": self.pretrain, "seeds": list(self.seeds),
                "alphas": list(self.alphas), "members": [t.relpath for t in self.trials]}


def group_populations(trials: list[Trial], size: int) -> list[PopulationJob]:
    """Trials grouped by (task, method, pretrain) into populations of at most ``size`` members.

    Every population is a product seeds x alphas: with at least as many slots as seeds, a
    population takes all seeds at ``size // len(seeds)`` alphas; otherwise one alpha and
    ``size`` seeds."""
    if size < 1:
        raise ConfigError(f"--population-size must be >= 1, got {size}.")
    jobs: list[PopulationJob] = []
    for (task, method, pretrain), ts in group_by(trials, lambda t: (t.task, t.method, t.pretrain)).items():
        seeds = list(dict.fromkeys(t.seed for t in ts))
        alphas = list(dict.fromkeys(t.alpha for t in ts))
        if len(seeds) <= size:
            per = max(1, size // len(seeds))
            jobs += [PopulationJob(task, method, pretrain, tuple(seeds), tuple(alphas[i:i + per]))
                     for i in range(0, len(alphas), per)]
        else:
            jobs += [PopulationJob(task, method, pretrain, tuple(seeds[i:i + size]), (a,))
                     for a in alphas for i in range(0, len(seeds), size)]
    return jobs


def method_label(method: str, pretrain: str | None) -> str:
    return method if pretrain is None else f"{method}-{pretrain}"


def format_alpha(alpha: float) -> str:
    """Shortest exact decimal for a grid alpha (grid values are rounded to 1e-6)."""
    text = f"{alpha:.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def _as_list(value: Any, field: str) -> list[Any]:
    if value is None:
        return []
    if isinstance(value, str):
        return [v.strip() for v in value.split(",") if v.strip()]
    if isinstance(value, (list, tuple)):
        return list(value)
    if isinstance(value, (int, float)):
        return [value]
    raise ConfigError(f"Grid field {field!r} must be a comma-separated string or a list, got {value!r}.")


def parse_seeds(value: Any) -> list[int]:
    """The grid's seeds (configs.members.parse_seeds) in increasing order: the trials' order."""
    return sorted(members.parse_seeds(value, "seeds"))


def parse_methods(value: Any) -> list[tuple[str, str | None]]:
    """Methods as `(method, pretrain)`; BOTO's pre-training is written `boto-cql` or `boto+cql`."""
    out: list[tuple[str, str | None]] = []
    for item in _as_list(value, "methods"):
        text = str(item).strip().lower()
        sep = next((s for s in "+-:" if s in text), None)
        method, pretrain = text.split(sep, 1) if sep else (text, None)
        if method not in METHODS:
            raise ConfigError(
                f"Grid field 'methods': unknown method {item!r}. Known: {', '.join(METHODS)}; "
                "BOTO with another pre-training is written boto-cql (or boto+cql)."
            )
        if pretrain is not None and (method != "boto" or pretrain not in PRETRAIN_ALGOS):
            raise ConfigError(
                f"Grid field 'methods': {item!r} is not valid; only boto takes a pre-training "
                f"suffix, one of {', '.join(PRETRAIN_ALGOS)} (e.g. boto-iql)."
            )
        out.append((method, pretrain))
    return list(dict.fromkeys(out))


def parse_overrides(value: Any) -> dict[str, str]:
    """`["online.steps=2000", ...]` or a YAML mapping -> `{dotted.path: value}`."""
    if isinstance(value, dict):
        items = list(flat_overrides(value).items())
    else:
        items = []
        for item in _as_list(value, "overrides"):
            text = str(item)
            if "=" not in text:
                raise ConfigError(
                    f"Override {text!r} has no '='. Write overrides as dotted.path=value, e.g. "
                    "--set online.steps=2000."
                )
            key, val = text.split("=", 1)
            items.append((key.strip().lstrip("-"), val.strip()))
    if not all(key for key, _ in items):
        raise ConfigError("An override has an empty name; write dotted.path=value.")
    return {key: str(val) for key, val in items}  # YAML's true, null: "True", "None", as the command line writes them


# Overrides that name a file or folder. Trials run in their own folders under --out, not where the
# sweep was started, so a relative path would name another place there: each is made absolute
# against the folder the sweep starts in (data.path only where it exists: it may be a Minari id).
PATH_OVERRIDES = ("pretrained", "data.path", "data.demos")


def absolute_paths(overrides: dict[str, str]) -> dict[str, str]:
    out = dict(overrides)
    for key in PATH_OVERRIDES:
        value = out.get(key)
        if value is None or value in ("", "None"):
            continue
        path = Path(value).expanduser()
        if key == "pretrained" and not path.is_dir():
            raise ConfigError(
                f"--set pretrained={value}: no such directory (from {os.getcwd()}). Point it at a run, population or "
                f"sweep directory whose pre-training finished, relative to the folder you start the sweep in or "
                f"absolute."
            )
        if key == "pretrained" or path.exists():
            out[key] = os.path.abspath(path)
    return out


@dataclasses.dataclass
class Grid:
    tasks: list[str]
    methods: list[tuple[str, str | None]]
    seeds: list[int]
    alphas: list[float] = dataclasses.field(default_factory=list)  # empty: the task presets
    overrides: dict[str, str] = dataclasses.field(default_factory=dict)
    profile: str | None = None

    def trials(self) -> list[Trial]:
        return [Trial(task, method, seed, alpha, pretrain) for task in self.tasks for method, pretrain in self.methods
                for alpha in (self.alphas if method == "boto" and self.alphas else [None]) for seed in self.seeds]

    def config(self, unit: Trial | PopulationJob):
        """The resolved, validated RunConfig a trial or population runs (configs.build.make_config)."""
        return make_config(self.overrides, **unit.fields, profile=self.profile)

    def to_json(self) -> dict[str, Any]:
        return {
            "tasks": list(self.tasks),
            "methods": [method_label(m, p) for m, p in self.methods],
            "seeds": list(self.seeds),
            "alphas": list(self.alphas),
            "overrides": dict(self.overrides),
            "profile": self.profile,
        }

    def __post_init__(self) -> None:
        for field in ("tasks", "methods", "seeds"):
            if not getattr(self, field):
                raise ConfigError(
                    f"The sweep grid has no {field}. Give --{field} on the command line or a "
                    f"'{field}:' entry in the --grid YAML file."
                )
        if self.alphas and not any(m == "boto" for m, _ in self.methods):
            raise ConfigError(
                "The sweep grid lists alphas but no boto method; alpha is BOTO's bias controller "
                "and applies to boto only. Add boto to --methods or drop --alphas."
            )
        n = len(self.tasks) * len(self.methods) * max(1, len(self.alphas)) * len(self.seeds)
        if n > MAX_TRIALS:  # counted before the trial list is built
            raise ConfigError(f"The sweep grid has about {n:,} trials; at most {MAX_TRIALS:,} are allowed. Give fewer "
                              f"tasks, methods, seeds or alphas (or split the grid into several sweeps).")


MAX_TRIALS = 100_000  # a grid's trials: far more than a study runs, few enough to list


class _GridLoader(yaml.SafeLoader):
    """A safe YAML loader with YAML 1.2 numbers: PyYAML's 1.1 rules read `-1:1:0.1` as the
    base-60 number -3660.9, not the alpha range the user wrote."""


_NUM_TAGS = ("tag:yaml.org,2002:int", "tag:yaml.org,2002:float")
_GridLoader.yaml_implicit_resolvers = {ch: [(tag, rx) for tag, rx in resolvers if tag not in _NUM_TAGS]
                                       for ch, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}
_GridLoader.add_implicit_resolver(_NUM_TAGS[0], re.compile(r"^[-+]?[0-9]+$"), list("-+0123456789"))
_GridLoader.add_implicit_resolver(
    _NUM_TAGS[1],
    re.compile(r"^[-+]?(\.[0-9]+|[0-9]+(\.[0-9]*)?)([eE][-+]?[0-9]+)?$|^[-+]?\.(inf|Inf|INF)$|^\.(nan|NaN|NAN)$"),
    list("-+0123456789."),
)


GRID_LIMIT = 1 << 20  # bytes of a --grid file: a few lines of YAML


def load_grid_file(path: str | Path) -> dict[str, Any]:
    """The fields of a ``--grid`` YAML file: a regular file (a link to one is fine; a FIFO would
    hang, /dev/zero never end) of at most ``GRID_LIMIT`` bytes."""
    path = Path(path)
    try:
        text = read_bounded(os.path.realpath(path), GRID_LIMIT)
    except FileNotFoundError:
        raise ConfigError(f"Grid file {path} does not exist; check the --grid path.") from None
    except (OSError, ValueError) as err:
        raise ConfigError(f"--grid {path}: {err}; give a YAML file (tasks, methods, seeds, ...).") from None
    try:
        data = yaml.load(text, Loader=_GridLoader)  # noqa: S506 (a SafeLoader)
    except yaml.YAMLError as err:
        raise ConfigError(f"Grid file {path} is not valid YAML: {err}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"Grid file {path} must be a YAML mapping with tasks, methods, seeds, ...")
    known = {"tasks", "methods", "seeds", "alphas", "overrides", "profile"}
    if unknown := set(data) - known:
        raise ConfigError(f"Grid file {path} has unknown field(s) {sorted(unknown)}; known fields are {sorted(known)}.")
    return data


def build_grid(file_fields: dict[str, Any] | None = None, *, tasks: Any = None, methods: Any = None, seeds: Any = None,
               alphas: Any = None, overrides: Any = None, profile: str | None = None) -> Grid:
    """Command-line values win over the file's; overrides from both are merged."""
    f = file_fields or {}
    return Grid(
        tasks=list(dict.fromkeys(str(t) for t in _as_list(tasks if tasks is not None else f.get("tasks"), "tasks"))),
        methods=parse_methods(methods if methods is not None else f.get("methods")),
        seeds=parse_seeds(seeds if seeds is not None else f.get("seeds")),
        alphas=parse_alphas(alphas if alphas is not None else f.get("alphas"), "alphas"),
        overrides=absolute_paths({**parse_overrides(f.get("overrides")), **parse_overrides(overrides)}),
        profile=profile if profile is not None else f.get("profile"),
    )


"""The task registry: one ``TaskSpec`` per task botorl knows (docs/CONTRACTS.md, "Tasks"): how
to make its env, where its offline data come from, the reward transform, the horizon, the success
metric, the paper's per-task settings (Table 2 / B.1) and its domain's network sizes (WSRL's and
Cal-QL's code; docs/methods.md, "Reference settings"), as plain data the presets read.
"""

from __future__ import annotations

import difflib
import importlib
from dataclasses import dataclass, field
from functools import cache, partial
from typing import Callable

import gymnasium as gym
from gymnasium.envs.registration import EnvSpec
from gymnasium.wrappers import TimeLimit

from botorl.envs.bandit import ACTION_DIM as BANDIT_ACTION_DIM
from botorl.errors import ConfigError


@dataclass(frozen=True)
class PaperSettings:
    """The paper's per-task BOTO settings (Table 2, appendix B.1)."""

    alpha: float
    boto_steps: int
    log_sigma: float


@dataclass(frozen=True)
class NetworkSizes:
    """Hidden layer widths, pre-training's and fine-tuning's (docs/methods.md, "Reference settings")."""

    critic: tuple[int, ...]
    actor: tuple[int, ...]


@dataclass(frozen=True)
class DatasetSource:
    """Where a task's offline data come from: ``kind`` "minari" (``ref``: the dataset id),
    "calql_npy" (``ref``: the expert and BC file names, joined by ","), "generated" (``ref``: the
    generator's task name) or "user" (``ref``: the file, "" = held in memory)."""

    kind: str
    ref: str
    obs_keys: tuple[str, ...] | None = None

    def describe(self) -> str:
        return {"minari": f"Minari {self.ref}", "calql_npy": f"Cal-QL {self.ref.replace(',', ' + ')}",
                "user": f"yours ({self.ref or 'in memory'})"}.get(self.kind, f"generated ({self.ref})")


@dataclass(frozen=True)
class TaskSpec:
    name: str
    domain: str  # "antmaze" | "kitchen" | "adroit" | "pointmaze" | "bandit"
    env_factory: Callable[[int | None], gym.Env] = field(repr=False)
    max_episode_steps: int
    success_mode: str  # "any": max over the episode; "last": value at the final step
    reward_scale: float
    reward_bias: float
    dataset_source: DatasetSource
    obs_dim: int
    action_dim: int
    networks: NetworkSizes
    paper: PaperSettings | None = None
    description: str = ""
    user: "UserTask | None" = field(default=None, repr=False)  # a user's own task's env (envs/user.py)
    # returns of a poor and a good policy (D4RL's names): with both, a task without success is
    # reported in the normalised score (botorl/envs/metric.py)
    ref_min_score: float | None = None
    ref_max_score: float | None = None

    @property
    def generated(self) -> bool:
        """botorl makes the task's data itself."""
        return self.dataset_source.kind == "generated"

    def make_env(self, seed: int = 0, *, evaluation: bool = False) -> gym.Env:
        """The wrapped env with the task's horizon. ``evaluation`` makes no difference: online
        training and evaluation use the same env, as in WSRL/Cal-QL."""
        return TimeLimit(self.env_factory(seed), self.max_episode_steps)  # truncation, not termination

    def gym_spec(self):
        """A Gymnasium ``EnvSpec`` that makes this task's env (with its horizon: no TimeLimit
        added), recorded in the Minari datasets botorl writes for ``recover_environment()``."""
        return EnvSpec(id=f"botorl/{self.name}-v0", entry_point="botorl.envs.registry:make_gym_env",
                       kwargs={"task": self.name}, disable_env_checker=True)


def make_gym_env(task: str, seed: int = 0, **_render) -> gym.Env:
    """``gym.make``'s entry point of ``gym_spec`` (``_render``: Gymnasium's ``render_mode``)."""
    return get_task(task).make_env(seed)


ANTMAZE_NET = NetworkSizes(critic=(256,) * 4, actor=(256,) * 2)
ADROIT_NET = NetworkSizes(critic=(512,) * 3, actor=(512,) * 2)
KITCHEN_NET = NetworkSizes(critic=(512,) * 3, actor=(512,) * 3)
# Our choices for the non-paper tasks: pointmaze is the antmaze stand-in, so it gets antmaze's
# networks; the one-step bandits and a user's task without a paper domain SAC's usual 2 x 256
# (docs/own-task.md).
SMALL_NET = NetworkSizes(critic=(256, 256), actor=(256, 256))
DOMAIN_NETS = {"antmaze": ANTMAZE_NET, "adroit": ADROIT_NET, "kitchen": KITCHEN_NET, "pointmaze": ANTMAZE_NET,
               "custom": SMALL_NET}


def _make(entry: str, *args) -> gym.Env:
    """``entry`` ("module:function" of this package) called with ``args``; imported on first use."""
    module, func = entry.split(":")
    return getattr(importlib.import_module(f"botorl.envs.{module}"), func)(*args)


@cache
def _tasks() -> dict[str, TaskSpec]:
    """The registry of this process (built on first use; ``register`` adds to it)."""
    # lazy: kitchen imports mujoco (through compat); a task's module loads when first used (``_make``)
    from botorl.envs.kitchen import MIXED_TASKS, PARTIAL_TASKS

    ant = dict(domain="antmaze", max_episode_steps=1000, success_mode="any", reward_scale=10.0, reward_bias=-5.0,
               obs_dim=29, action_dim=8, networks=ANTMAZE_NET)
    kitchen = dict(domain="kitchen", max_episode_steps=280, success_mode="last", reward_scale=1.0, reward_bias=-4.0,
                   obs_dim=59, action_dim=9, networks=KITCHEN_NET)
    door = dict(domain="adroit", env_factory=partial(_make, "adroit:make_adroit", "door"), max_episode_steps=200,
                success_mode="any", reward_scale=10.0, reward_bias=5.0, obs_dim=39, action_dim=28, networks=ADROIT_NET)
    ant_keys = ("achieved_goal", "observation")
    specs = [
        TaskSpec(name="antmaze-large-diverse-v2", env_factory=partial(_make, "antmaze:make_antmaze_task", "large"),
                 dataset_source=DatasetSource("minari", "D4RL/antmaze/large-diverse-v1", ant_keys),
                 paper=PaperSettings(alpha=-1.0, boto_steps=100_000, log_sigma=-30.0),
                 description="ant, large maze, start (1,1) -> goal (7,9); D4RL diverse data", **ant),
        TaskSpec(name="antmaze-large-play-v2", env_factory=partial(_make, "antmaze:make_antmaze_task", "large"),
                 dataset_source=DatasetSource("minari", "D4RL/antmaze/large-play-v1", ant_keys),
                 paper=PaperSettings(alpha=-0.7, boto_steps=100_000, log_sigma=-20.0),
                 description="ant, large maze, start (1,1) -> goal (7,9); D4RL play data", **ant),
        TaskSpec(name="kitchen-partial-v0", env_factory=partial(_make, "kitchen:make_kitchen", PARTIAL_TASKS),
                 dataset_source=DatasetSource("minari", "D4RL/kitchen/partial-v2", ("observation",)),
                 paper=PaperSettings(alpha=0.8, boto_steps=250_000, log_sigma=-20.0),
                 description="Franka kitchen: microwave, kettle, light switch, slide cabinet", **kitchen),
        TaskSpec(name="kitchen-mixed-v0", env_factory=partial(_make, "kitchen:make_kitchen", MIXED_TASKS),
                 dataset_source=DatasetSource("minari", "D4RL/kitchen/mixed-v2", ("observation",)),
                 paper=PaperSettings(alpha=1.0, boto_steps=250_000, log_sigma=-20.0),
                 description="Franka kitchen: microwave, kettle, bottom burner, light switch", **kitchen),
        TaskSpec(name="door-binary-v0", dataset_source=DatasetSource("calql_npy", "door2_sparse.npy,door_bc_sparse4.npy"),
                 paper=PaperSettings(alpha=0.0, boto_steps=100_000, log_sigma=-20.0),
                 description="Adroit door, binary reward (Cal-QL); human demos + BC rollouts", **door),
        TaskSpec(name="pen-binary-v0", dataset_source=DatasetSource("calql_npy", "pen2_sparse.npy,pen_bc_sparse4.npy"),
                 paper=PaperSettings(alpha=-0.9, boto_steps=100_000, log_sigma=-20.0),
                 description="Adroit pen, binary reward (Cal-QL); human demos + BC rollouts",
                 **dict(door, env_factory=partial(_make, "adroit:make_adroit", "pen"), max_episode_steps=100,
                        obs_dim=45, action_dim=24)),
        TaskSpec(name="door-binary-local", dataset_source=DatasetSource("generated", "door-binary-local"),
                 description="door-binary with data made here: the 25 DAPG demos + BC rollouts", **door),
    ]
    # antmaze with data made here (botorl.data.generators.antmaze); D4RL's horizons.
    specs += [TaskSpec(
        name=f"antmaze-{maze}-{kind}-local", env_factory=partial(_make, "antmaze:make_antmaze_task", maze),
        dataset_source=DatasetSource("generated", f"antmaze-{maze}-{kind}-local"),
        description=f"ant, {maze} maze, D4RL evaluation start/goal; {kind} data made here (waypoint ant)",
        **dict(ant, max_episode_steps=horizon)) for maze, kind, horizon in (
            ("large", "diverse", 1000), ("large", "play", 1000), ("medium", "diverse", 1000), ("medium", "play", 1000),
            ("umaze", "diverse", 700))]
    # pointmaze: reward transform like antmaze (sparse goal reward, termination at the goal).
    specs += [TaskSpec(
        name=f"pointmaze-{maze}", domain="pointmaze", env_factory=partial(_make, "pointmaze:make_pointmaze", maze),
        max_episode_steps=horizon, success_mode="any", reward_scale=10.0, reward_bias=-5.0,
        dataset_source=DatasetSource("generated", f"pointmaze-{maze}"), obs_dim=4, action_dim=2,
        networks=ANTMAZE_NET, description=f"point mass, D4RL maze2d {maze} map, fixed start and goal; maze2d-style data")
        for maze, horizon in (("umaze", 300), ("medium", 600), ("large", 800))]
    specs += [TaskSpec(
        name=f"bandit-{kind}", domain="bandit", env_factory=partial(_make, "bandit:BanditEnv", kind),
        max_episode_steps=1, success_mode="last", reward_scale=1.0, reward_bias=0.0,
        dataset_source=DatasetSource("generated", f"bandit-{kind}"), obs_dim=1, action_dim=BANDIT_ACTION_DIM[kind],
        networks=SMALL_NET, description=f"one-step bandit: {desc}")
        for kind, desc in (("pinwheel", "2-D pinwheel action data (paper Fig. 2)"), ("1d", "1-D bandit (paper Fig. 3)"))]
    return {s.name: s for s in specs}


def list_tasks() -> list[TaskSpec]:
    return list(_tasks().values())


def register(spec: TaskSpec) -> TaskSpec:
    """Add a user's task to the registry of this process (again under the same name replaces it);
    botorl's own task names are refused."""
    tasks = _tasks()
    if spec.name in tasks and tasks[spec.name].user is None:
        raise ConfigError(f"task name {spec.name!r} is one of botorl's tasks; register yours under another name.")
    if spec.user is None:
        raise ConfigError(f"task {spec.name!r}: only user tasks (TaskSpec.user set) can be registered.")
    tasks[spec.name] = spec
    return spec


def is_registered(name: str) -> bool:
    return name in _tasks()


def get_task(name: str) -> TaskSpec:
    tasks = _tasks()
    if name in tasks:
        return tasks[name]
    close = difflib.get_close_matches(name, list(tasks), n=1, cutoff=0.5)
    hint = f" Did you mean {close[0]!r}?" if close else ""
    raise ConfigError(f"unknown task {name!r}.{hint} Valid tasks: {', '.join(tasks)}. "
                      "`botorl tasks` lists them with the state of their data.")

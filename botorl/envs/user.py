"""A task of the user's own: their Gymnasium env, behind the same ``TaskEnv`` every task has.

``make_env(seed)`` (a callable of the user's, or ``MODULE:FUNCTION`` imported by name) returns a
Gymnasium env with a ``Box`` action space and a ``Box`` or (nested) ``Dict`` of ``Box``
observation space; ``UserTaskEnv`` makes it look like every botorl task (CONTRACTS.md, "Tasks").
The transformations are pure NumPy functions so that code outside botorl (``botorl.load_policy``,
an exporter) and the data loaders apply exactly the same ones.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from botorl.envs.metric import check_refs
from botorl.envs.registry import DOMAIN_NETS, DatasetSource, TaskSpec
from botorl.envs.wrappers import TaskEnv
from botorl.errors import ConfigError


# ------------------------------------------------------------------ the pure transformations
def obs_keys_of(space) -> tuple[str, ...] | None:
    """The leaves of a ``Dict`` observation space (or of a dict observation batch) in flattening
    order (sorted keys at every level, nested ones as ``"a/b"``); None for a ``Box`` (or an array).
    Any other space is a ConfigError."""
    if isinstance(space, spaces.Box) or not isinstance(space, (spaces.Space, dict)):
        return None
    if isinstance(space, (spaces.Dict, dict)):
        keys: list[str] = []
        children = space.spaces if isinstance(space, spaces.Dict) else space
        for k in sorted(children):
            inner = obs_keys_of(children[k])
            keys += [str(k)] if inner is None else [f"{k}/{i}" for i in inner]
        return tuple(keys)
    raise ConfigError(f"the env's observation space is {space}; botorl takes a gymnasium.spaces.Box, or a Dict of "
                      "Boxes (flattened in sorted key order). Wrap the env so that it observes a Box (e.g. "
                      "gymnasium.wrappers.FlattenObservation).")


def _leaf(obs: Any, key: str):
    node = obs
    for part in key.split("/"):
        if not isinstance(node, dict) or part not in node:
            raise ConfigError(f"observation has no key {key!r} (it has {sorted(node) if isinstance(node, dict) else type(node).__name__}); "
                              f"the env's observations changed since the task was registered.")
        node = node[part]
    return node


def flatten_obs(obs: Any, keys: tuple[str, ...] | None = None, *, batched: bool = False) -> np.ndarray:
    """One observation -> (D,) float32, or a batch (``batched``: every leaf (B, ...)) -> (B, D);
    ``keys``: ``obs_keys_of`` of the env's space (None: an array observation, only reshaped)."""
    if keys is None:
        a = np.asarray(obs, dtype=np.float32)
        return a.reshape(a.shape[0], -1) if batched else a.reshape(-1)
    leaves = [np.asarray(_leaf(obs, k), dtype=np.float32) for k in keys]
    if batched:
        return np.concatenate([x.reshape(x.shape[0], -1) for x in leaves], axis=-1)
    return np.concatenate([x.reshape(-1) for x in leaves])


def action_to_env(actions, low, high) -> np.ndarray:
    """Actions in [-1, 1] -> the env's ``[low, high]`` (affine; clipped to the box)."""
    a = np.clip(np.asarray(actions, dtype=np.float64), -1.0, 1.0)
    low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
    return np.clip(low + (a + 1.0) * 0.5 * (high - low), low, high)


def action_from_env(actions, low, high) -> np.ndarray:
    """The inverse of ``action_to_env`` (not clipped: logged actions outside the box stay
    outside, so that a check can report them)."""
    a = np.asarray(actions, dtype=np.float64)
    low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
    return 2.0 * (a - low) / (high - low) - 1.0


def is_unit_box(low, high) -> bool:
    return bool(np.all(np.asarray(low) == -1.0) and np.all(np.asarray(high) == 1.0))


# ------------------------------------------------------------------ what botorl knows of the env
@dataclass(frozen=True)
class UserTask:
    """What a user task's env is, found by ``probe`` (recorded in the run's config.json as ``env``)."""

    obs_keys: tuple[str, ...] | None  # None: a Box observation space
    obs_dim: int
    action_dim: int
    action_low: tuple[float, ...]
    action_high: tuple[float, ...]
    success_key: str | None  # None: success is off
    success_off: str | None = None  # why success is off (None while it is on)
    entry: str | None = None  # "module:function", when make_env can be imported by that name
    path: str | None = None  # the folder put on sys.path to import ``entry`` (None: importable as is)


class UnitActions(gym.ActionWrapper):
    """The env's ``Box(low, high)`` seen as ``Box(-1, 1)``."""

    def __init__(self, env: gym.Env, low, high):
        super().__init__(env)
        self._low = np.asarray(low, np.float64)
        self._high = np.asarray(high, np.float64)
        self._dtype = env.action_space.dtype
        self.action_space = spaces.Box(-1.0, 1.0, shape=env.action_space.shape, dtype=np.float32)

    def action(self, action):
        return action_to_env(action, self._low, self._high).astype(self._dtype).reshape(self.env.action_space.shape)


class UserTaskEnv(TaskEnv):
    """A user's env as a botorl task (see the module docstring)."""

    def __init__(self, env: gym.Env, task: UserTask, seed: int | None = None):
        self._keys = task.obs_keys
        self._success_key = task.success_key
        super().__init__(UnitActions(env, task.action_low, task.action_high), task.obs_dim, seed)

    def _observe(self, obs):
        return flatten_obs(obs, self._keys)

    def _task_step(self, obs, reward, terminated, info):
        s = np.asarray(info.get(self._success_key, 0.0), dtype=np.float64)
        return reward, terminated, float(s.max()) if s.size else 0.0


# ------------------------------------------------------------------ entry points
def split_entry(entry: str) -> tuple[str, str]:
    module, sep, func = str(entry).partition(":")
    if not sep or not module or not func or ":" in func:
        raise ConfigError(f"--env {entry!r}: give the env's entry point as MODULE:FUNCTION, e.g. --env mytask:make_env "
                          f"(make_env(seed) in mytask.py in the current folder, returning a Gymnasium env).")
    return module, func


def import_entry(entry: str) -> tuple[Callable[[int], gym.Env], str | None]:
    """Import ``MODULE:FUNCTION`` (searching the current folder, as ``python -m`` does, and
    PYTHONPATH) -> (the function, the folder it was found in; None for an installed module).
    ``entry`` is one the user gave (``--env``, ``register_task``): never one a file names, and no
    folder a file names is put on ``sys.path`` (a run directory is data)."""
    module_name, func_name = split_entry(entry)
    cwd = os.getcwd()
    if cwd not in sys.path:
        sys.path.insert(0, cwd)
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as err:
        raise ConfigError(f"--env {entry}: cannot import module {module_name!r} ({err}). botorl looks in the current "
                          f"folder ({cwd}) and on PYTHONPATH; run from the folder holding "
                          f"{module_name.replace('.', '/')}.py or add its folder to PYTHONPATH.") from None
    except (Exception, SystemExit) as err:  # the user's module failed (or called sys.exit) while importing
        raise ConfigError(f"--env {entry}: importing module {module_name!r} failed: {type(err).__name__}: {err}. "
                          f"Fix the module (`python -c \"import {module_name}\"` shows the traceback).") from None
    func = getattr(module, func_name, None)
    if not callable(func):
        names = [n for n in dir(module) if not n.startswith("_") and callable(getattr(module, n))]
        raise ConfigError(f"--env {entry}: module {module_name!r} ({getattr(module, '__file__', '?')}) has no "
                          f"function {func_name!r}; its callables: {', '.join(names) or 'none'}.")
    return func, _found_in(module, module_name)


def _found_in(module, module_name: str) -> str | None:
    """The sys.path folder ``module_name`` was imported from (its top package's parent), to search
    again in another process; None for an installed module (site-packages) that any process finds."""
    file = getattr(module, "__file__", None)
    if not file:
        return None
    root = Path(file).resolve().parents[module_name.count(".")]
    root = root.parent if Path(file).name == "__init__.py" else root
    return None if {"site-packages", "dist-packages"} & set(root.parts) else str(root)


def entry_of(make_env: Callable) -> tuple[str | None, str | None]:
    """(``module:qualname``, the folder to import it from) of a function that can be imported
    again by name in another process; (None, None) for one defined in ``__main__``, a lambda, a
    closure or a partial (those are never pickled: such a task is registered again by its script)."""
    module_name = getattr(make_env, "__module__", None)
    qual = getattr(make_env, "__qualname__", "")
    if not module_name or module_name == "__main__" or "<" in qual or "." in qual:
        return None, None
    module = sys.modules.get(module_name)
    if module is None or getattr(module, qual, None) is not make_env:
        return None, None
    return f"{module_name}:{qual}", _found_in(module, module_name)


# ------------------------------------------------------------------ probing the env
# The probe's look for the success key: at most this many random steps and seconds (an env that
# never says success, with a huge horizon, must not hold botorl up).
PROBE_STEPS = 10_000
PROBE_SECONDS = 20.0


def probe(make_env: Callable[[int], gym.Env], max_episode_steps: int, success_key: str | None,
          *, name: str, key_given: bool = False) -> UserTask:
    """Make one env and check its spaces; one episode of random actions looks for
    ``info[success_key]``: if it never appears success is off (``UserTask.success_off`` says why),
    or, with ``key_given`` (a key the user named), a ConfigError."""
    what = f"task {name!r}: make_env"
    try:
        env = make_env(0)
    except (Exception, SystemExit) as err:  # sys.exit in make_env is a failure too, never botorl's exit 0
        raise ConfigError(f"{what}(0) raised {type(err).__name__}: {err}. make_env(seed) must return a Gymnasium "
                          f"env.") from None
    if not isinstance(env, gym.Env):
        raise ConfigError(f"{what}(0) returned {type(env).__name__}, not a gymnasium.Env.")
    try:
        act = env.action_space
        if not isinstance(act, spaces.Box):
            raise ConfigError(f"{what}(0) has the action space {act}; botorl's agents act in continuous boxes and need "
                              "a gymnasium.spaces.Box action space (a discrete task needs another library).")
        low, high = (np.broadcast_to(np.asarray(b, np.float64), act.shape).reshape(-1) for b in (act.low, act.high))
        if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high)) and np.all(high > low)):
            raise ConfigError(f"{what}(0) has the action space {act} with unbounded or empty dimensions; botorl "
                              f"rescales the box to [-1, 1] and needs finite low < high in every dimension.")
        if len(act.shape) != 1:
            raise ConfigError(f"{what}(0) has actions of shape {act.shape}; botorl needs a flat Box (shape (A,)).")
        keys = obs_keys_of(env.observation_space)
        obs, info = env.reset(seed=0)
        flat = flatten_obs(obs, keys)
        seen = success_key is not None and success_key in info
        rng = np.random.default_rng(0)
        deadline = time.monotonic() + PROBE_SECONDS
        for _ in range(min(int(max_episode_steps), PROBE_STEPS)):  # a look, bounded whatever the horizon
            if seen or success_key is None or time.monotonic() > deadline:
                break
            a = rng.uniform(low, high).astype(act.dtype).reshape(act.shape)
            obs, _, terminated, truncated, info = env.step(a)
            seen = success_key in info
            if terminated or truncated:
                break
    except ConfigError:
        raise
    except (Exception, SystemExit) as err:
        raise ConfigError(f"task {name!r}: the env failed on reset/step ({type(err).__name__}: {err}).") from None
    finally:
        with contextlib.suppress(Exception):
            env.close()
    off = None
    if success_key is None:
        off = "success_key=None: success is off, botorl reports the episode return instead"
    elif not seen:
        found = ", ".join(sorted(map(str, info))) or "none"
        if key_given:
            raise ConfigError(f"task {name!r}: --success-key {success_key!r} is not in the env's info (keys seen: "
                              f"{found}). Name the info key that says the episode succeeded, or leave --success-key "
                              f"out (success is then off if the env has no {'success'!r} key).")
        off = (f"the env's info has no {success_key!r} key (keys seen: {found}), so success is off: botorl "
               f"reports the episode return instead (the normalised score with ref_min_score and ref_max_score); "
               f"pass success_key (--success-key) naming the info key if the env does mark success")
    return UserTask(obs_keys=keys, obs_dim=int(flat.shape[0]), action_dim=int(low.shape[0]),
                    action_low=tuple(low.tolist()), action_high=tuple(high.tolist()),
                    success_key=None if off else success_key, success_off=off)


# ------------------------------------------------------------------ the task
PAPER_DOMAINS = ("antmaze", "adroit", "kitchen", "pointmaze")


def make_spec(name: str, make_env: Callable[[int], gym.Env], task: UserTask, *, max_episode_steps: int,
              domain: str | None = None, reward_scale: float = 1.0, reward_bias: float = 0.0,
              data_ref: str | None = None, ref_min_score: float | None = None, ref_max_score: float | None = None):
    """The ``TaskSpec`` of a user's task (not registered yet: ``registry.register``)."""
    if not isinstance(name, str) or not name or any(c.isspace() for c in name) or "/" in name:
        raise ConfigError(f"task name {name!r}: give a non-empty name without spaces or '/', e.g. 'mytask'.")
    if domain is not None and domain not in PAPER_DOMAINS:
        raise ConfigError(f"task {name!r}: domain {domain!r} is not one of {', '.join(PAPER_DOMAINS)} (a paper domain "
                          f"whose presets the task takes), or None for the defaults of the docs' Your own task page.")
    if isinstance(max_episode_steps, bool) or not isinstance(max_episode_steps, (int, np.integer)) or max_episode_steps < 1:
        raise ConfigError(f"task {name!r}: max_episode_steps (--env-max-steps) = {max_episode_steps!r}; give the "
                          f"episode length limit, a positive integer.")
    for what, v in (("reward_scale", reward_scale), ("reward_bias", reward_bias)):
        if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)) or not np.isfinite(v):
            raise ConfigError(f"task {name!r}: {what} = {v!r}; give a finite number.")
    ref_min_score, ref_max_score = check_refs(ref_min_score, ref_max_score, f"task {name!r}")
    dom = domain or "custom"
    return TaskSpec(
        name=name, domain=dom, env_factory=lambda seed: UserTaskEnv(make_env(seed), task, seed),
        max_episode_steps=int(max_episode_steps),
        success_mode="any", reward_scale=float(reward_scale), reward_bias=float(reward_bias),
        dataset_source=DatasetSource("user", data_ref or ""),
        obs_dim=task.obs_dim, action_dim=task.action_dim, networks=DOMAIN_NETS[dom],
        description=f"your task ({task.entry or 'registered from Python'})", user=task,
        ref_min_score=ref_min_score, ref_max_score=ref_max_score,
    )

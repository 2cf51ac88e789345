"""The offline data of a user's own task (botorl/envs/user.py), in any of the forms of
docs/own-task.md, "Your data". Logged actions are in the env's own units, mapped to [-1, 1] with
``action_from_env``; rewards stay raw. Data given in memory are held for the process
(``hold``); a run whose data came from a file re-reads the file.
"""

from __future__ import annotations

import os
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from botorl.data import loaders
from botorl.data.dataset import TRANSITION_FIELDS, Dataset, numeric, validate
from botorl.data.safe import check_npz
from botorl.envs.user import UserTask, action_from_env, flatten_obs, is_unit_box
from botorl.errors import DataFormatError, DatasetNotFoundError

REQUIRED = TRANSITION_FIELDS
OPTIONAL = ("timeouts", "episode_ends")

# task name -> (the data's path or "", the Dataset) registered in this process
_HELD: dict[str, tuple[str, Dataset]] = {}


def hold(name: str, ref: str, ds: Dataset) -> None:
    _HELD[name] = (ref, ds)


def _unit(task: UserTask):
    if is_unit_box(task.action_low, task.action_high):
        return None
    return lambda a: action_from_env(a, task.action_low, task.action_high)


def _obs(x, task: UserTask, field: str, source: str) -> np.ndarray:
    if isinstance(x, Mapping):
        if task.obs_keys is None:
            raise DataFormatError(f"{source}: {field} is a dict ({sorted(x)}) but the env observes an array; give "
                                  f"{field} as an (N, {task.obs_dim}) array.")
        try:
            return flatten_obs(x, task.obs_keys, batched=True)
        except Exception as err:
            raise DataFormatError(f"{source}: {field} cannot be flattened as the env's dict observations "
                                  f"(keys {', '.join(task.obs_keys)}): {err}") from None
    a = numeric(x, field, source).astype(np.float32)
    return a.reshape(a.shape[0], -1) if a.ndim >= 2 else a.reshape(-1, 1)


def check_dims(ds: Dataset, task: UserTask, source: str) -> None:
    """The data's widths against the env's (DataFormatError naming both)."""
    _check_obs(ds.obs_dim, task, source, "observations")
    if ds.action_dim != task.action_dim:
        raise DataFormatError(f"{source}: actions have {ds.action_dim} dimensions, but the env's action space has "
                              f"{task.action_dim}. The data were logged from another env; log the actions passed to "
                              "this env's step().")


def _check_obs(width: int, task: UserTask, source: str, field: str) -> None:
    if width != task.obs_dim:
        layout = f" (the env's dict observation flattened as {', '.join(task.obs_keys)})" if task.obs_keys else ""
        raise DataFormatError(f"{source}: {field} have {width} dimensions, but the env's have {task.obs_dim}{layout}. "
                              "The data were logged from another env (or another version of it); log them from this "
                              "env's observations.")


def from_arrays(arrays: Mapping, task: UserTask, *, source: str) -> Dataset:
    """A dict of arrays (see the module docstring) -> Dataset, actions mapped to [-1, 1]."""
    missing = [k for k in REQUIRED if k not in arrays]
    if missing:
        raise DataFormatError(f"{source}: missing {', '.join(map(repr, missing))} (found "
                              f"{', '.join(map(repr, sorted(arrays)))}). The data need {', '.join(REQUIRED)} with one "
                              f"row per transition, and optionally {' and '.join(OPTIONAL)}.")
    obs = _obs(arrays["observations"], task, "observations", source)
    nobs = _obs(arrays["next_observations"], task, "next_observations", source)
    _check_obs(obs.shape[1], task, source, "observations")
    _check_obs(nobs.shape[1], task, source, "next_observations")
    act = numeric(arrays["actions"], "actions", source).astype(np.float64)
    act = act.reshape(-1, 1) if act.ndim == 1 else act.reshape(act.shape[0], -1)
    if act.shape[1] == task.action_dim and not is_unit_box(task.action_low, task.action_high):
        act = action_from_env(act, task.action_low, task.action_high)
    flags = {}
    for k in ("terminals",) + OPTIONAL:
        if k in arrays and arrays[k] is not None:
            v = numeric(arrays[k], k, source)
            if v.dtype.kind == "f" and not np.isfinite(v).all():
                raise DataFormatError(f"{source}: field {k!r} has NaN/inf values; give 0/1 (or booleans) per row.")
            flags[k] = v.reshape(-1).astype(bool)
    ends = flags.get("episode_ends")
    if ends is None:
        ends = flags["terminals"] | flags["timeouts"] if "timeouts" in flags else None
    ds = Dataset(obs, act, arrays["rewards"], nobs, flags["terminals"], ends,
                 metadata={"source": source, "format": "arrays"})
    check_dims(ds, task, source)
    return validate(ds, action_tolerance=np.inf)


def _grouped(npz) -> dict:
    """``.npz`` keys ``a/b`` as nested dicts (dict observations)."""
    out: dict = {}
    for k in npz.files:
        node = out
        parts = k.split("/")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = npz[k]
    return out


def load_file(path: str | os.PathLike, task: UserTask, *, max_episode_steps: int | None = None) -> Dataset:
    """A user's data file (see the module docstring) -> Dataset."""
    text = str(path)
    p = Path(text).expanduser()
    suffix = p.suffix.lower()
    if suffix == ".npz":
        if not p.is_file():
            raise DatasetNotFoundError(f"--data.path {text}: no such file. Give the .npz your data were saved to "
                                       f"(np.savez(path, observations=..., actions=..., ...)).")
        check_npz(p)  # a regular file whose headers fit, before any array is inflated
        try:
            with np.load(p, allow_pickle=False) as npz:
                arrays = _grouped(npz)
        except (zipfile.BadZipFile, EOFError) as err:
            raise DataFormatError(f"{p}: not a readable .npz file ({type(err).__name__}: {err}).") from None
        except ValueError as err:
            raise DataFormatError(f"{p}: cannot be read without pickle ({err}); save plain arrays with np.savez.") from None
        except OSError as err:
            raise DataFormatError(f"{p}: not a readable .npz file ({err}).") from None
        try:
            return from_arrays(arrays, task, source=str(p))
        except (ValueError, TypeError) as err:  # bytes or strings where numbers belong
            raise DataFormatError(f"{p}: its arrays cannot be read as numbers ({type(err).__name__}: {err}).") from None
    if suffix in (".hdf5", ".h5") and p.name != "main_data.hdf5":
        ds = loaders.load_d4rl_hdf5(p, max_episode_steps=max_episode_steps, actions_to_unit=_unit(task),
                                    action_tolerance=np.inf)
    elif p.is_dir() or p.name == "main_data.hdf5" or not suffix:
        ds = loaders.load_minari(p if p.exists() else text, obs_keys=task.obs_keys, actions_to_unit=_unit(task),
                                 action_tolerance=np.inf, success_info_key=task.success_key or "success")
    else:
        raise DataFormatError(f"--data.path {text}: unknown data format {suffix!r}; a task of your own reads a .npz "
                              f"(observations, actions, rewards, next_observations, terminals), a D4RL .hdf5, or a "
                              f"Minari dataset (folder or id).")
    check_dims(ds, task, str(p))
    return ds


def to_dataset(data, task: UserTask, *, name: str, max_episode_steps: int | None = None) -> tuple[str, Dataset]:
    """(the data's path or "" for data in memory, the Dataset) of what ``register_task`` was given."""
    if isinstance(data, Dataset):
        check_dims(data, task, f"the dataset of task {name!r}")
        return "", validate(data, action_tolerance=np.inf)
    if isinstance(data, (str, os.PathLike)):
        ref = str(Path(data).expanduser().resolve()) if Path(data).expanduser().exists() else str(data)
        return ref, load_file(ref, task, max_episode_steps=max_episode_steps)
    if isinstance(data, Mapping):
        return "", from_arrays(data, task, source=f"the dataset of task {name!r}")
    raise DataFormatError(f"task {name!r}: dataset is a {type(data).__name__}; give a dict of arrays (observations, "
                          f"actions, rewards, next_observations, terminals), a path (.npz, D4RL .hdf5, Minari folder "
                          f"or id) or a botorl Dataset.")


def load_task_data(spec, path: str | os.PathLike | None = None, *, action_tolerance: float = 1e-3) -> Dataset:
    """The data of a user's task: those held in memory for it, or the file (``path``, else the one
    it was registered with). Logged actions outside the env's box beyond ``action_tolerance`` (in
    [-1, 1] units) are a DataFormatError."""
    task: UserTask = spec.user
    ref = str(path) if path is not None else spec.dataset_source.ref
    got = _HELD.get(spec.name)
    ds = got[1] if got is not None and got[0] == ref else None
    if ds is None:
        if not ref:
            raise DatasetNotFoundError(f"task {spec.name!r}: its data were given in memory to botorl.register_task in "
                                       "another process. Register the task again (the same script) before "
                                       "botorl.resume / botorl.run, or save the data to a .npz and register that path.")
        ds = load_file(ref, task, max_episode_steps=spec.max_episode_steps)
    if ds.raw_action_max > 1.0 + action_tolerance:
        bounds = "[-1, 1]" if is_unit_box(task.action_low, task.action_high) else \
            f"low {list(task.action_low)}, high {list(task.action_high)}"
        raise DataFormatError(f"{ds.metadata.get('source', spec.name)}: the logged actions leave the env's action box "
                              f"({bounds}): {ds.raw_action_max:.4g} in botorl's [-1, 1] units, beyond the tolerance "
                              f"{action_tolerance:g}. Log the actions in the env's own units (those passed to "
                              "env.step), or raise --data.action_tolerance to clip them.")
    return ds

"""Readers for the real dataset formats of the paper's tasks, each returning a validated
``Dataset`` with raw rewards (docs/tasks.md, "Loaders"): D4RL hdf5, Minari (by id or folder),
Cal-QL's adroit-binary ``.npy`` pair, DAPG human demos (pickle or botorl's ``.npz``).

Pickle-based files are read by ``safe.read_plain_pickle`` (plain data only, nothing called), and
only from a path the user named, never by searching, and never inside ``refuse_pickle(origin)``
(paths read back from a run directory) unless ``--allow-pickle``.
"""

from __future__ import annotations

import contextlib
import contextvars
import json
import os
from pathlib import Path
from typing import Callable, Sequence

import h5py
import numpy as np
from minari import MinariDataset

from botorl.data.dataset import Dataset, numeric, validate
from botorl.data.minari_io import SPLIT_KEY, FlatCacheInvalid, minari_root, read_flat, rebuild_flat
from botorl.data.safe import check_hdf5, check_npz, read_plain_pickle, regular_file
from botorl.envs.adroit import DOOR_SUCCESS_ANGLE
from botorl.envs.registry import get_task, is_registered
from botorl.envs.user import flatten_obs, obs_keys_of
from botorl.errors import ConfigError, DataFormatError, DatasetNotFoundError, warn

# ----------------------------------------------------------------------------- hints

# Where Cal-QL's adroit-binary data come from (nakamotoo/Cal-QL README, "Adroit Binary").
CALQL_DATA_INSTRUCTIONS = (
    "Download the adroit-binary offline data linked in the Cal-QL README "
    "(https://github.com/nakamotoo/Cal-QL, section 'Adroit Binary': a Google Drive zip of "
    "demonstrations/offpolicy_hand_data/*.npy), unzip it, and pass the folder or the two files "
    "explicitly (e.g. `botorl run --task door-binary-v0 --data.path /path/to/offpolicy_hand_data`, "
    "or --data.path EXPERT.npy,BC.npy). These files are pickles, so botorl only opens files you name."
)


def download_hint(name: str) -> str:
    """How a user gets the data of a task name or Minari id (one sentence or two)."""
    src = get_task(name).dataset_source if is_registered(name) else None
    if src is not None and src.kind == "minari":  # the paper's D4RL tasks' current Minari ports
        return (
            f"{name} is read from its Minari port {src.ref}: run `minari download {src.ref}` (needs "
            f"`pip install \"minari[hdf5]\"` and network) once; it lands in {minari_root()} "
            "(set MINARI_DATASETS_PATH to use another folder)."
        )
    if src is not None and src.kind == "calql_npy":
        expert, bc = src.ref.split(",")
        return f"{name} needs Cal-QL's {expert} and {bc}. {CALQL_DATA_INSTRUCTIONS}"
    if "/" in name or name.rsplit("-v", 1)[-1].isdigit():
        return (
            f"If {name} is a public Minari dataset, run `minari download {name}`; it lands in "
            f"{minari_root()} (set MINARI_DATASETS_PATH to use another folder)."
        )
    return "Check the path, or generate the data with `botorl data generate TASK`."


def dataset_not_found(name: str, looked: Sequence[str | os.PathLike], hint: str | None = None) -> DatasetNotFoundError:
    """The error for ``name`` (task name, Minari id or file) not found in ``looked``."""
    where = ", ".join(str(p) for p in looked) or "(nowhere)"
    return DatasetNotFoundError(
        f"dataset {name} was not found; botorl looked in: {where}. {hint or download_hint(name)}"
    )


def _require_file(path: str | os.PathLike, what: str) -> Path:
    p = Path(path).expanduser()
    if not p.exists():
        raise dataset_not_found(str(p), [p], f"Check the path of the {what} file.")
    if not p.is_dir():
        regular_file(p, f"{what} file")  # a FIFO or device is never opened (it would hang or never end)
    return p


def join_episodes(episodes: list[dict], metadata: dict) -> Dataset:
    """One Dataset of per-episode rows: dicts of observations, next_observations, actions,
    rewards, terminals, optionally episode_ends (default: the last row) and success (an info
    kept only when every episode has it)."""
    for e in episodes:
        e.setdefault("episode_ends", np.arange(len(e["rewards"])) == len(e["rewards"]) - 1)
    rows = {k: np.concatenate([e[k] for e in episodes]) for k in episodes[0] if all(k in e for e in episodes)}
    success = rows.pop("success", None)
    return Dataset(**rows, infos=None if success is None else {"success": success}, metadata=metadata)


# ----------------------------------------------------------------------------- D4RL hdf5


def _qlearning_rows(terminals: np.ndarray, timeouts: np.ndarray | None, max_episode_steps: int | None):
    """(kept row indices, their episode_end flags) of D4RL's ``qlearning_dataset``
    (terminate_on_end=False; Farama-Foundation/D4RL d4rl/__init__.py): rows i < N - 1 only, next
    obs = row i + 1; a ``timeouts`` row (without ``timeouts``, as in kitchen: the row where the
    per-episode step counter reaches ``max_episode_steps - 1``) starts no transition and resets the
    counter; a terminal row is kept (done) and resets the counter."""
    n = terminals.shape[0]
    skipped = np.zeros(n - 1, bool) if timeouts is None else timeouts[: n - 1].astype(bool)
    if timeouts is None and max_episode_steps is not None:
        step = 0
        term = terminals.astype(bool).tolist()
        for i in range(n - 1):
            skipped[i] = step == max_episode_steps - 1
            step = 0 if skipped[i] or term[i] else step + 1
    idx = np.flatnonzero(~skipped)
    # A kept row ends its episode if it is terminal, or the next row is a skipped
    # time-out row, or it is the last kept row.
    ends = terminals[idx].astype(bool) | np.concatenate([skipped, [True]])[idx + 1]
    if len(ends):
        ends[-1] = True
    return idx, ends


def load_d4rl_hdf5(path: str | os.PathLike, *, max_episode_steps: int | None = None, obs_dim: int | None = None,
                   action_dim: int | None = None, action_tolerance: float = 1e-3,
                   actions_to_unit: Callable[[np.ndarray], np.ndarray] | None = None) -> Dataset:
    """A D4RL hdf5 file, as ``qlearning_dataset`` reads it (``_qlearning_rows``); ``infos/success``
    or ``infos/goal_achieved`` become ``infos["success"]``. ``actions_to_unit`` maps the file's
    actions to [-1, 1] (a user's env with other bounds)."""
    p = _require_file(path, "D4RL hdf5")
    try:
        f = h5py.File(p, "r")
    except OSError as err:
        raise DataFormatError(f"{p}: not a readable HDF5 file ({err}). A D4RL dataset is an .hdf5 file with "
                              "datasets observations, actions, rewards, terminals; re-download it.") from None
    with f:
        check_hdf5(f, p)  # external storage or links could read any file, or hang on a FIFO
        missing = [k for k in ("observations", "actions", "rewards", "terminals") if k not in f]
        if missing:
            raise DataFormatError(f"{p}: missing D4RL field(s) {missing} (found {sorted(f.keys())}). A D4RL file "
                                  "needs observations, actions, rewards, terminals (and usually timeouts).")
        try:
            # each field as stored, its dtype checked (complex numbers, byte strings), then converted
            obs = numeric(f["observations"], "observations", str(p)).astype(np.float32)
            act = numeric(f["actions"], "actions", str(p)).astype(np.float32)
            rew = numeric(f["rewards"], "rewards", str(p)).astype(np.float32).reshape(-1)
            term = numeric(f["terminals"], "terminals", str(p)).reshape(-1).astype(bool)
            if actions_to_unit is not None:
                act = np.asarray(actions_to_unit(act), np.float32)
            tout = numeric(f["timeouts"], "timeouts", str(p)).reshape(-1).astype(bool) if "timeouts" in f else None
            key = next((k for k in ("infos/success", "infos/goal_achieved") if k in f), None)
            success = None if key is None else np.asarray(f[key]).reshape(-1).astype(np.float32)
        except (ValueError, TypeError, OSError, AttributeError) as err:  # bytes where numbers belong, a group
            raise DataFormatError(f"{p}: a D4RL field cannot be read as numbers ({type(err).__name__}: {err}); "
                                  f"observations, actions, rewards, terminals must be numeric datasets.") from None
    n = obs.shape[0]
    lens = {k: v.shape[0] for k, v in (("observations", obs), ("actions", act), ("rewards", rew), ("terminals", term),
                                       ("timeouts", tout)) if v is not None}
    if len(set(lens.values())) != 1:
        raise DataFormatError(f"{p}: fields have different lengths {lens}; the file is truncated or corrupt.")
    if n < 2:
        raise DataFormatError(f"{p}: only {n} rows; a D4RL file needs at least 2 to form a transition.")
    if obs.ndim != 2 or act.ndim != 2:
        raise DataFormatError(f"{p}: observations {obs.shape} and actions {act.shape} must be 2-D.")
    idx, ends = _qlearning_rows(term, tout, max_episode_steps)
    infos = {}
    if success is not None and success.shape[0] == n:
        infos["success"] = success[idx + 1]  # success after the step, like the env's info
    ds = Dataset(
        obs[idx], act[idx], rew[idx], obs[idx + 1], term[idx], ends,
        infos=infos, metadata={"source": str(p), "format": "d4rl-hdf5"},
    )
    return validate(ds, obs_dim, action_dim, action_tolerance)


# ----------------------------------------------------------------------------- Minari


def _h5_tree(node):
    if isinstance(node, h5py.Dataset):
        return node[()]
    return {k: _h5_tree(node[k]) for k in node.keys()}


def _minari_episodes(mds, data_path: Path):
    """(id, {observations, actions, rewards, terminations, infos}) per episode, in order.

    Minari's hdf5 storage is read directly with h5py, about 10x faster than ``iterate_episodes``
    on 10^4 short episodes; other storage formats go through Minari's API."""
    main = data_path / "main_data.hdf5"
    try:
        if not main.exists():
            for ep in mds.iterate_episodes():
                yield ep.id, {"observations": ep.observations, "actions": ep.actions, "rewards": ep.rewards,
                              "terminations": ep.terminations, "infos": ep.infos}
            return
        with h5py.File(main, "r") as f:
            check_hdf5(f, main)
            names = sorted((k for k in f.keys() if k.startswith("episode_")), key=lambda k: int(k.split("_")[1]))
            for name in names:
                g = f[name]
                yield int(name.split("_")[1]), {
                    "observations": _h5_tree(g["observations"]), "infos": _h5_tree(g["infos"]) if "infos" in g else {},
                    **{k: g[k][()] for k in ("actions", "rewards", "terminations")}}
    except DataFormatError:
        raise
    except Exception as err:
        raise DataFormatError(
            f"{main} cannot be read ({type(err).__name__}: {err}); the file is truncated "
            "or damaged. Regenerate it (`botorl data generate TASK --overwrite`) or download the dataset again."
        ) from None


def _minari_rows(mds, data_path: Path, obs_keys, actions_to_unit, success_info_key: str) -> list[dict]:
    """Each episode of a Minari dataset as rows (``join_episodes``'s input)."""
    episodes = []
    for ep_id, ep in _minari_episodes(mds, data_path):
        obs = ep["observations"]
        keys = obs_keys_of(obs) if obs_keys is None or not isinstance(obs, dict) else tuple(obs_keys)
        try:
            o = flatten_obs(obs, keys, batched=True)
        except ConfigError:
            raise DataFormatError(f"{data_path}: observation keys {list(keys)} are not all in the dataset's dict "
                                  f"observations ({obs_keys_of(obs)}); check obs_keys.") from None
        t = len(ep["rewards"])
        actions = np.asarray(ep["actions"], np.float32)
        if actions_to_unit is not None:
            actions = np.asarray(actions_to_unit(actions), np.float32)
        if o.shape[0] != t + 1 or actions.shape[0] != t:
            raise DataFormatError(f"{data_path}: episode {ep_id} has {o.shape[0]} observations and "
                                  f"{actions.shape[0]} actions for {t} rewards (expected T + 1, T, T).")
        if t == 0:
            continue
        info = ep["infos"] if isinstance(ep["infos"], dict) else {}
        end = np.zeros(t, bool)
        # botorl's writer splits an episode where it is not continuous; join it back.
        end[-1] = not (SPLIT_KEY in info and np.asarray(info[SPLIT_KEY]).reshape(-1)[-1] > 0)
        episodes.append({"observations": o[:-1], "next_observations": o[1:], "actions": actions.reshape(t, -1),
                         "rewards": np.asarray(ep["rewards"], np.float32).reshape(t),
                         "terminals": np.asarray(ep["terminations"]).reshape(t).astype(bool), "episode_ends": end})
        if success_info_key in info:
            episodes[-1]["success"] = np.asarray(info[success_info_key], np.float32).reshape(-1)[-t:]
    return episodes


def load_minari(id_or_path: str | os.PathLike, *, obs_keys: Sequence[str] | None = None, obs_dim: int | None = None,
                action_dim: int | None = None, action_tolerance: float = 1e-3, success_info_key: str = "success",
                actions_to_unit: Callable[[np.ndarray], np.ndarray] | None = None) -> Dataset:
    """A Minari dataset, by id (from ``$MINARI_DATASETS_PATH``, never downloaded) or by path (a
    ``Path``, an existing path, or one starting with ``.``/``~``: the dataset folder, its ``data``
    folder or its ``main_data.hdf5``).

    Dict observations go through ``flatten_obs`` (sorted keys unless ``obs_keys``). An episode of
    T steps gives T transitions, the last an episode end, and the last T entries of
    ``infos[success_info_key]`` as ``infos["success"]``.
    """
    given = Path(id_or_path).expanduser()
    as_path = (isinstance(id_or_path, os.PathLike) or given.is_absolute() or str(id_or_path).startswith((".", "~"))
               or given.exists())
    if not as_path:
        data_path = minari_root() / str(id_or_path) / "data"
    elif given.is_file() and given.name != "main_data.hdf5":
        raise DataFormatError(f"{given} exists, but it is a file and this task reads a Minari dataset: give the "
                              "dataset's folder (the one holding data/main_data.hdf5 and data/metadata.json) or its "
                              "main_data.hdf5. A D4RL .hdf5 file is read by `botorl data info FILE` / "
                              "botorl.data.loaders.load_d4rl_hdf5, not as a Minari dataset.")
    else:
        data_path = given.parent if given.is_file() else given
        if (data_path / "data").is_dir():
            data_path = data_path / "data"
    rebuild = False
    if obs_keys is None and data_path.name == "data" and actions_to_unit is None:
        try:
            flat = read_flat(data_path.parent)
        except FlatCacheInvalid as err:
            flat = None
            rebuild = True
            warn(f"not using the flat cache: {err}; reading the Minari data in {data_path} and rebuilding the cache.")
        if flat is not None:
            return validate(flat, obs_dim, action_dim, action_tolerance)
    if not (data_path / "metadata.json").exists() and not (data_path / "main_data.hdf5").exists():
        if as_path and given.is_dir():
            raise DataFormatError(f"{given} exists but is not a Minari dataset folder: it has neither "
                                  "data/main_data.hdf5 nor data/metadata.json. Pass the folder of a Minari dataset (or "
                                  "regenerate it with `botorl data generate`).")
        raise dataset_not_found(str(id_or_path), [data_path], None if not as_path else
                                "Pass the folder of a Minari dataset (it contains data/main_data.hdf5 and data/metadata.json).")
    for fname in ("main_data.hdf5", "metadata.json"):  # Minari opens both: a FIFO would hang it
        if os.path.lexists(data_path / fname):
            regular_file(data_path / fname, "Minari data file")
    try:
        mds = MinariDataset(data_path)
    except Exception as err:  # minari raises assorted errors on broken folders
        raise DataFormatError(f"{data_path}: not a readable Minari dataset ({type(err).__name__}: {err}). "
                              "Re-download it with `minari download <id>` or rewrite it.") from None
    try:
        episodes = _minari_rows(mds, data_path, obs_keys, actions_to_unit, success_info_key)
    except (ValueError, TypeError) as err:  # bytes or strings where numbers belong
        raise DataFormatError(f"{data_path}: an episode's arrays cannot be read as numbers ({type(err).__name__}: "
                              f"{err}); observations, actions, rewards and terminations must be numeric.") from None
    if not episodes:
        raise DataFormatError(f"{data_path}: the Minari dataset has no steps.")
    meta = {"source": str(data_path.parent if data_path.name == "data" else data_path), "format": "minari",
            "minari_id": mds.id}
    with contextlib.suppress(Exception):
        extra = mds.storage.metadata.get("botorl_metadata")
        if extra:
            meta["botorl"] = json.loads(extra)
    ds = join_episodes(episodes, meta)
    if rebuild and "botorl" in meta:  # only botorl's own datasets carry a flat copy
        rebuild_flat(ds, data_path.parent)
    return validate(ds, obs_dim, action_dim, action_tolerance)


# ----------------------------------------------------------------------------- pickles

# The DAPG door demos reach |a| = 1.37 (5.6% of the action entries); the simulator clamps controls
# to their range, so clipping them (as Cal-QL's ``clip_action`` does) keeps what was applied: the
# adroit loaders accept |a| <= 2 and clip.
ADROIT_ACTION_TOLERANCE = 1.0


# Where the path being loaded came from when it was not named by the user (e.g. "the run
# directory's config.json"); None = the user named it (command line or API call).
_PICKLE_REFUSED: contextvars.ContextVar[str | None] = contextvars.ContextVar("botorl_pickle_refused", default=None)


@contextlib.contextmanager
def refuse_pickle(origin: str):
    """Within this block, pickle-based files are refused: their paths came from ``origin``."""
    token = _PICKLE_REFUSED.set(origin)
    try:
        yield
    finally:
        _PICKLE_REFUSED.reset(token)


def _load_pickle_array(path: Path, what: str):
    """A pickle-based file: without pickle when the data allow it, else only from a path the user named."""
    origin = _PICKLE_REFUSED.get()
    regular_file(path, what)
    if path.suffix == ".npy":
        try:
            return np.load(path, allow_pickle=False)  # plain arrays need no pickle
        except ValueError as err:
            if "allow_pickle" not in str(err):
                raise DataFormatError(f"{path}: cannot be read as a {what} ({err}).") from None
        except Exception as err:
            raise DataFormatError(f"{path}: cannot be read as a {what} ({type(err).__name__}: {err}).") from None
    if origin is not None:
        raise DataFormatError(f"{path}: this {what} is a pickle, and its path comes from {origin}, not from you; a "
                              "pickle can run code when loaded, so botorl does not open it. If you trust the file, "
                              "pass --allow-pickle to `botorl resume`/`botorl eval`, or name it yourself: `botorl run "
                              f"... --data.path {path}`.")
    try:
        return read_plain_pickle(path, what)
    except DataFormatError:
        raise
    except Exception as err:
        raise DataFormatError(f"{path}: cannot be read as a {what} ({type(err).__name__}: {err}). Check that this "
                              "is the right file (pickle-based files are opened only from paths you name).") from None


def _as_list_of_dicts(obj, path: Path, what: str) -> list[dict]:
    if isinstance(obj, np.ndarray) and obj.dtype == object:
        obj = list(obj.reshape(-1))
    if not isinstance(obj, (list, tuple)) or not obj or not all(isinstance(t, dict) for t in obj):
        raise DataFormatError(f"{path}: expected a {what}: a non-empty list (or object array) of per-trajectory "
                              f"dicts, got {type(obj).__name__}.")
    return list(obj)


def _need(traj: dict, keys: Sequence[str], path: Path, i: int) -> None:
    missing = [k for k in keys if k not in traj]
    if missing:
        raise DataFormatError(f"{path}: trajectory {i} lacks key(s) {missing} (has {sorted(traj)}).")


def _stack_obs(seq, key: str | None, path: Path, i: int) -> np.ndarray:
    try:
        if key is not None:
            return np.stack([np.asarray(x[key], np.float32) for x in seq])
        return np.asarray(seq, np.float32).reshape(len(seq), -1)
    except (KeyError, TypeError, IndexError, ValueError) as err:
        raise DataFormatError(f"{path}: trajectory {i}: observations are not "
                              f"{'dicts with ' + repr(key) if key else 'numeric arrays'} ({err}).") from None


def calql_cut(rows: dict, success: np.ndarray, drop_unsuccessful: bool = True) -> dict | None:
    """Cal-QL's rule for a binary-reward trajectory: ``rows`` cut after the last ``success`` step,
    every success step terminal; one that never succeeds is None if ``drop_unsuccessful``, else kept whole."""
    hits = np.flatnonzero(success)
    if not len(hits) and drop_unsuccessful:
        return None
    end = int(hits[-1]) + 1 if len(hits) else len(success)
    return {**{k: v[:end] for k, v in rows.items()}, "terminals": success[:end],
            "success": success[:end].astype(np.float32)}


def load_calql_adroit(expert_path: str | os.PathLike | None, bc_path: str | os.PathLike | None = None, *,
                      obs_dim: int | None = None, action_dim: int | None = None,
                      action_tolerance: float = ADROIT_ACTION_TOLERANCE) -> Dataset:
    """Cal-QL's adroit-binary data: expert ``*2_sparse.npy`` and/or BC ``*_bc_sparse4.npy``
    (pickled object arrays of per-trajectory dicts), processed as Cal-QL does (nakamotoo/Cal-QL,
    JaxCQL/replay_buffer.py ``get_hand_dataset_with_mc_calculation``).

    The expert file's observations are per-step dicts (``"state_observation"``) and its
    ``rewards`` may have one entry too many; the BC file's are plain (T, 1) arrays. Rewards are
    {-1, 0} (0 = success): a trajectory without a 0 is dropped, the others are cut after their
    last success; every success step is terminal (``dones = rewards == reward_pos``). Cal-QL's
    MC returns: ``with_mc_returns(0.99, sparse_negative_reward=-1)``.
    """
    parts = []
    for path, kind in ((expert_path, "expert"), (bc_path, "bc")):
        if path is None:
            continue
        p = _require_file(path, f"Cal-QL {kind} .npy")
        trajs = _as_list_of_dicts(_load_pickle_array(p, "Cal-QL .npy"), p, "Cal-QL adroit .npy file")
        episodes = []
        for i, tr in enumerate(trajs):
            _need(tr, ("observations", "next_observations", "actions", "rewards"), p, i)
            # the expert file's observations are dicts, the BC file's arrays (either file may be either)
            key = "state_observation" if len(tr["observations"]) and isinstance(tr["observations"][0], dict) else None
            o = _stack_obs(tr["observations"], key, p, i)
            no = _stack_obs(tr["next_observations"], key, p, i)
            a = np.asarray(tr["actions"], np.float32).reshape(len(o), -1)
            r = np.atleast_1d(np.asarray(tr["rewards"], np.float32).squeeze())[: len(o)]
            if not (len(o) == len(no) == len(a) == len(r)):
                raise DataFormatError(f"{p}: trajectory {i} has mismatched lengths: {len(o)} observations, "
                                      f"{len(no)} next_observations, {len(a)} actions, {len(r)} rewards.")
            ep = calql_cut({"observations": o, "next_observations": no, "actions": a, "rewards": r}, r == 0.0)
            if ep is not None:  # never succeeds: Cal-QL drops it
                episodes.append(ep)
        if not episodes:
            raise DataFormatError(f"{p}: no trajectory reaches a success (reward 0); nothing to load.")
        parts.append(join_episodes(episodes, {"source": str(p), "format": f"calql-adroit-{kind}"}))
    if not parts:
        raise dataset_not_found("door-binary-v0 / pen-binary-v0", ["(no path given)"], CALQL_DATA_INSTRUCTIONS)
    ds = parts[0] if len(parts) == 1 else parts[0].concat(parts[1])
    return validate(ds, obs_dim, action_dim, action_tolerance)


def door_success(observations: np.ndarray) -> np.ndarray:
    """Adroit door opened: hinge angle ``obs[..., 28]`` at the success angle (DAPG / Gymnasium-Robotics)."""
    return np.asarray(observations)[..., 28] >= DOOR_SUCCESS_ANGLE


def dapg_trajectories(p: Path, keys: Sequence[str] = ("observations", "actions", "rewards")) -> list[dict]:
    """The demos of a DAPG demo file (pickle or botorl's ``.npz``), one dict of ``keys`` each."""
    if p.suffix == ".npz":
        check_npz(p)
        try:
            with np.load(p, allow_pickle=False) as z:
                missing = [k for k in (*keys, "episode_lengths") if k not in z.files]
                if missing:
                    raise DataFormatError(f"{p}: .npz lacks key(s) {missing} (has {sorted(z.files)}); botorl's DAPG "
                                          "demo file has observations, actions, rewards, episode_lengths.")
                arrays = {k: np.asarray(z[k]) for k in keys}
                lens = np.asarray(z["episode_lengths"]).astype(np.int64).reshape(-1)
                rows = {k: v.shape[0] for k, v in arrays.items()}
        except DataFormatError:
            raise
        except Exception as err:
            raise DataFormatError(f"{p}: not a readable .npz file ({type(err).__name__}: {err}).") from None
        if (lens <= 0).any() or any(n != lens.sum() for n in rows.values()):
            raise DataFormatError(f"{p}: lengths do not fit: episode_lengths sum to {int(lens.sum())}, "
                                  + ", ".join(f"{k} {n}" for k, n in rows.items()) + ".")
        bounds = np.concatenate([[0], np.cumsum(lens)])
        return [{k: v[s:e] for k, v in arrays.items()} for s, e in zip(bounds[:-1], bounds[1:])]
    trajs = _as_list_of_dicts(_load_pickle_array(p, "DAPG demo pickle"), p, "DAPG demo pickle")
    out = []
    for i, tr in enumerate(trajs):
        _need(tr, keys, p, i)
        o = np.asarray(tr["observations"], np.float32)
        a = np.asarray(tr["actions"], np.float32)
        r = np.asarray(tr.get("rewards", np.zeros(len(o))), np.float32).reshape(-1)  # present unless not in keys
        if not (len(o) == len(a) == len(r)) or o.ndim != 2 or a.ndim != 2:
            raise DataFormatError(f"{p}: demo {i} has observations {o.shape}, actions {a.shape}, rewards {r.shape}; "
                                  "expected (T, O), (T, A), (T,).")
        out.append({"observations": o, "actions": a, "rewards": r})
    return out


def load_dapg_demos(path: str | os.PathLike, *, binary_reward: bool = False,
                    drop_unsuccessful: bool = True, obs_dim: int | None = None, action_dim: int | None = None,
                    action_tolerance: float = ADROIT_ACTION_TOLERANCE) -> Dataset:
    """DAPG human demos: the original list-of-dicts pickle or botorl's ``.npz``
    (botorl/data/assets/README.md describes its arrays).

    A demo of T recorded steps gives T - 1 transitions, one episode, no terminals.
    ``binary_reward=True`` (Cal-QL's "binary" task): reward = success - 1, the demo cut at its
    first success, which is terminal; demos that never succeed are dropped when
    ``drop_unsuccessful``, else kept with reward -1 throughout.
    """
    p = _require_file(path, "DAPG demo")
    trajs = dapg_trajectories(p)
    episodes = []
    for tr in trajs:
        o, a, r = tr["observations"], tr["actions"], tr["rewards"]
        if len(o) < 2:
            continue
        o_, no_, a_, r_ = o[:-1], o[1:], a[:-1], r[:-1].astype(np.float32)
        succ = np.asarray(door_success(no_), bool)
        term = np.zeros(len(o_), bool)
        if binary_reward:
            hit = np.flatnonzero(succ)
            if len(hit):
                cut = int(hit[0]) + 1
                o_, no_, a_, succ = o_[:cut], no_[:cut], a_[:cut], succ[:cut]
                term = succ  # cut at the first success: True at the last row only
            elif drop_unsuccessful:
                continue
            r_ = succ.astype(np.float32) - 1.0
        episodes.append({"observations": o_, "next_observations": no_, "actions": a_, "rewards": r_,
                         "terminals": term, "success": succ.astype(np.float32)})
    if not episodes:
        raise DataFormatError(f"{p}: no usable demo (all shorter than 2 steps or none succeeds).")
    ds = join_episodes(episodes, {"source": str(p), "format": "dapg-" + ("npz" if p.suffix == ".npz" else "pickle"),
                                   "binary_reward": binary_reward})
    return validate(ds, obs_dim, action_dim, action_tolerance)


def load_path(path: str | os.PathLike, **kwargs) -> Dataset:
    """Pick a loader by what ``path`` is (``botorl data info PATH``)."""
    p = _require_file(path, "dataset")
    if p.is_dir() or p.name == "main_data.hdf5":
        return load_minari(p, **kwargs)
    suffix = p.suffix.lower()
    if suffix in (".hdf5", ".h5"):
        return load_d4rl_hdf5(p, **kwargs)
    if suffix in (".npz", ".pickle", ".pkl"):
        return load_dapg_demos(p, **kwargs)
    if suffix == ".npy":
        obj = _as_list_of_dicts(_load_pickle_array(p, "Cal-QL .npy"), p, "Cal-QL adroit .npy file")
        first = obj[0].get("observations")
        is_expert = first is not None and len(first) and isinstance(first[0], dict)
        return load_calql_adroit(p, None, **kwargs) if is_expert else load_calql_adroit(None, p, **kwargs)
    raise DataFormatError(f"{p}: unknown dataset format {suffix!r}; botorl reads Minari folders, D4RL .hdf5, "
                          "DAPG .npz/.pickle and Cal-QL .npy files.")

"""Writing botorl datasets as Minari datasets, so any Minari-aware tool can read them.

Minari's own writer costs about 2.5 ms per episode (70 s for 1M pointmaze steps), so Minari only
makes ``metadata.json`` and the episodes go straight into ``main_data.hdf5`` in the layout of
Minari 0.5's ``HDF5Storage.update_episodes`` (about 0.7 ms per episode; tests compare the two
writers). Everything is written into a private temporary root next to the destination, then
moved into place with one ``rename``: a crash leaves no dataset or a complete one. botorl's
metadata is a JSON string under the metadata key ``botorl_metadata``.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import io
import json
import os
import shutil
import socket
import time
import uuid
import warnings
from pathlib import Path
from typing import Any
from unittest import mock

import gymnasium as gym
import h5py
import minari
import numpy as np
from h5py import h5a, h5d, h5g, h5s, h5t
from minari.data_collector import EpisodeBuffer
from minari.dataset.minari_dataset import parse_dataset_id
from tqdm import tqdm

from botorl.data.dataset import ACTION_CLIP, TRANSITION_FIELDS, Dataset, segments
from botorl.data.safe import check_npz, data_cap, regular_file
from botorl.errors import BotorlError, ConfigError
from botorl.io import atomic_write_bytes, file_sha256, pid_alive

# Marks an episode split that botorl had to make because next_observation[i] !=
# observation[i + 1] inside one episode (Minari stores one observation sequence per
# episode); load_minari joins such pieces back into one episode.
SPLIT_KEY = "botorl_split"

# Minari's hdf5 layout costs about 1-5 ms per episode to read, a minute for 1M pointmaze steps;
# the same rows stored flat beside the ``data`` folder (Minari ignores it) load at once.
FLAT_FILE = "botorl_flat.npz"
FLAT_FIELDS = TRANSITION_FIELDS + ("episode_ends",)  # the rows it holds (not mc_returns: a run makes its own)
# Temporary roots of write_minari: ``.botorl-tmp-<host>-<pid>-<random>``; one whose process is
# gone (a `botorl data generate` killed with -9) is removed by the next write into the root.
TMP_PREFIX = ".botorl-tmp-"
# A temporary root of another host (or of the old unnamed form) is removed after this long.
TMP_MAX_AGE_S = 24 * 3600


class FlatCacheInvalid(BotorlError):
    """The flat copy does not match its Minari source or its own recorded contents."""


def _content_sha256(arrays: dict[str, np.ndarray]) -> str:
    """Checksum of named arrays (name, dtype, shape and bytes, in name order)."""
    h = hashlib.sha256()
    for k in sorted(arrays):
        a = np.ascontiguousarray(arrays[k])
        h.update(f"{k}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _host() -> str:
    return socket.gethostname().replace("-", "_") or "host"


def clean_stale_tmp(root: Path) -> None:
    """Remove temporary roots left under ``root`` by writers that died (kill -9)."""
    try:
        entries = list(Path(root).iterdir())
    except OSError:
        return
    host = _host()
    for p in entries:
        if not p.name.startswith(TMP_PREFIX) or not p.is_dir():
            continue
        parts = p.name[len(TMP_PREFIX):].rsplit("-", 2)
        if len(parts) == 3 and parts[0] == host and parts[1].isdigit():
            stale = not pid_alive(int(parts[1]))
        else:  # another host's, or the old unnamed form: only when clearly abandoned
            try:
                stale = time.time() - p.stat().st_mtime > TMP_MAX_AGE_S
            except OSError:
                stale = False
        if stale:
            shutil.rmtree(p, ignore_errors=True)


def minari_root() -> Path:
    """Minari's dataset root: ``$MINARI_DATASETS_PATH`` or ``~/.minari/datasets``."""
    env = os.environ.get("MINARI_DATASETS_PATH")
    return Path(env) if env else Path.home() / ".minari" / "datasets"


def _cuts(ds: Dataset):
    """Episode (starts, ends) row ranges, and where a discontinuity forced a split."""
    # Discontinuities inside an episode force a split (see SPLIT_KEY).
    jump = np.zeros(len(ds), bool)
    jump[:-1] = ~ds.episode_ends[:-1] & np.any(ds.next_observations[:-1] != ds.observations[1:], axis=1)
    return *segments(ds.episode_ends | jump), jump


def _episodes(ds: Dataset):
    """Per episode of T steps: T + 1 observations, T actions, rewards, terminations, truncations (the
    last truncated unless terminal), infos of T + 1 entries (the first, Minari's reset info, 0)."""
    starts, ends, jump = _cuts(ds)
    infos_all = {k: np.asarray(ds.infos[k]) for k in sorted(ds.infos)}
    split_any = bool(jump.any())
    layout = _dict_layout(ds)
    for s, e in zip(starts.tolist(), ends.tolist()):
        obs = np.concatenate([ds.observations[s:e], ds.next_observations[e - 1 : e]])
        if layout:
            obs = _dict_obs(obs, layout, infos_all, s, e)
        term = ds.terminals[s:e]
        trunc = np.zeros(e - s, bool)
        trunc[-1] = not term[-1]
        infos: dict[str, Any] = {k: np.concatenate([np.zeros((1,) + v.shape[1:], v.dtype), v[s:e]])
                                 for k, v in infos_all.items()}
        if split_any:
            split = np.zeros(e - s + 1, np.float32)
            split[-1] = float(jump[e - 1])
            infos[SPLIT_KEY] = split
        yield obs, ds.actions[s:e], ds.rewards[s:e], term, trunc, infos


def _dict_obs(flat: np.ndarray, layout: dict, infos: dict, s: int, e: int) -> dict:
    """Dict observations of one episode (T + 1 rows), as ``metadata["minari_dict_obs"]`` describes
    them: ``{key: [start, stop]}`` (a slice of the flat rows) or ``{key: "infos:NAME"}`` (a
    per-row info, the last repeated), as Minari's D4RL/antmaze datasets store them."""
    out = {}
    for key, spec in layout.items():
        if isinstance(spec, str) and spec.startswith("infos:"):
            v = infos[spec[6:]][s:e]
            out[key] = np.concatenate([v, v[-1:]])
        else:
            out[key] = np.ascontiguousarray(flat[:, int(spec[0]) : int(spec[1])])
    return out


def _dict_layout(ds: Dataset):
    """The dict-observation layout of a fresh generated dataset, or of one read back."""
    return ds.metadata.get("minari_dict_obs") or (ds.metadata.get("botorl") or {}).get("minari_dict_obs")


def _observation_space(ds: Dataset):
    layout = _dict_layout(ds)
    if not layout:
        return gym.spaces.Box(-np.inf, np.inf, (ds.obs_dim,), np.float32)
    dims = {key: int(np.prod(np.asarray(ds.infos[spec[6:]]).shape[1:])) if isinstance(spec, str)
            else int(spec[1]) - int(spec[0]) for key, spec in layout.items()}
    return gym.spaces.Dict({k: gym.spaces.Box(-np.inf, np.inf, (d,), np.float64) for k, d in dims.items()})


def _write_episodes_h5(ds: Dataset, file_path: Path, progress: bool, name: str) -> tuple[int, int]:
    """Write every episode of ``ds`` into ``file_path`` in Minari's HDF5 layout; (episodes, steps).

    h5py's low-level calls with shared datatypes are about 2x faster than ``create_dataset``,
    and the in-memory ("core") driver writes the file once at close.
    """
    n_eps = len(_cuts(ds)[1])
    tid_of = functools.cache(functools.partial(h5t.py_create, logical=True))  # one datatype per dtype

    def write(gid, key: bytes, arr: np.ndarray):
        arr = np.ascontiguousarray(arr)
        dset = h5d.create(gid, key, tid_of(arr.dtype), h5s.create_simple(arr.shape))
        dset.write(h5s.ALL, h5s.ALL, arr)

    scalar = h5s.create(h5s.SCALAR)

    def attr(gid, key: bytes, value: int):
        a = np.asarray(value, np.int64)  # what h5py's ``attrs[key] = int`` stores
        h5a.create(gid, key, tid_of(a.dtype), scalar).write(a)

    episodes = tqdm(_episodes(ds), total=n_eps, desc=f"writing {name}", unit="episode", mininterval=1.0,
                    disable=not progress)
    # As Minari: the root group tracks the creation order of its episode groups.
    with h5py.File(file_path, "w", track_order=True, driver="core", backing_store=True) as f:
        root = f.id
        for ep_id, (obs, act, rew, term, trunc, infos) in enumerate(episodes):
            g = h5g.create(root, f"episode_{ep_id}".encode())
            attr(g, b"id", ep_id)
            attr(g, b"total_steps", len(rew))
            if isinstance(obs, dict):
                og = h5g.create(g, b"observations")
                for k, v in obs.items():
                    write(og, k.encode(), v)
            else:
                write(g, b"observations", obs)
            for key, v in ((b"actions", act), (b"rewards", rew), (b"terminations", term), (b"truncations", trunc)):
                write(g, key, v)
            if infos:
                ig = h5g.create(g, b"infos")
                for k, v in infos.items():
                    write(ig, k.encode(), v)
    return n_eps, len(ds)


def write_minari(dataset: Dataset, dataset_id: str | None = None, *, path: str | os.PathLike | None = None,
                 root: str | os.PathLike | None = None, overwrite: bool = False, description: str | None = None,
                 metadata: dict[str, Any] | None = None, algorithm_name: str = "botorl generator",
                 progress: bool = False, env_spec=None, _minari_writer: bool = False) -> Path:
    """Write ``dataset`` as a Minari dataset; returns its folder.

    Where: ``dataset_id`` under ``root`` (default: ``minari_root()``), or ``path``, a folder
    whose name is the id. ``metadata`` is stored with botorl's dataset metadata; ``env_spec``
    (``TaskSpec.gym_spec()``) is recorded so that ``recover_environment()`` works.
    """
    root_p = Path(root).expanduser() if root is not None else minari_root()
    if path is not None:
        p = Path(path).expanduser().resolve()
        root_p, dataset_id = p.parent, p.name
    elif dataset_id is None:
        raise ConfigError("write_minari needs a dataset_id or a path.")
    try:
        parse_dataset_id(dataset_id)
    except Exception:
        raise ConfigError(f"{dataset_id!r} is not a valid Minari dataset id: use (namespace/)name-v<N> with "
                          "letters, digits, '-' and '_' (e.g. botorl/pointmaze-large/steps1000000-seed0-v0).") from None
    final = root_p / dataset_id
    if final.exists() and not overwrite:
        raise BotorlError(f"a dataset already exists at {final}; pass overwrite=True (CLI: --overwrite) to "
                          "replace it, or choose another id.")
    root_p.mkdir(parents=True, exist_ok=True)
    clean_stale_tmp(root_p)
    tmp_root = root_p / f"{TMP_PREFIX}{_host()}-{os.getpid()}-{uuid.uuid4().hex[:12]}"
    obs_space = _observation_space(dataset)
    act_space = gym.spaces.Box(-1.0, 1.0, (dataset.action_dim,), np.float32)
    meta = {k: v for k, v in dataset.metadata.items() if k not in ("source",)}
    meta.update(metadata or {})
    meta["transitions"] = len(dataset)
    try:
        with mock.patch.dict(os.environ, MINARI_DATASETS_PATH=str(tmp_root)), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # Minari warns about every optional field left empty
            kwargs = dict(algorithm_name=algorithm_name, author="botorl", author_email="none",
                          code_permalink="https://github.com/botorl/botorl", action_space=act_space,
                          observation_space=obs_space, description=description or f"botorl dataset {dataset_id}",
                          env=env_spec)
            extra = {"botorl_metadata": json.dumps(meta, default=_json_default)}
            if _minari_writer:  # Minari's own (slow) writer, one EpisodeBuffer per episode; tests compare the two
                buffers = [EpisodeBuffer(id=i, observations=obs, actions=act, rewards=rew, terminations=term.copy(),
                                         truncations=trunc, infos=infos or None)
                           for i, (obs, act, rew, term, trunc, infos) in enumerate(_episodes(dataset))]
                mds = minari.create_dataset_from_buffers(
                    dataset_id, tqdm(buffers, desc=f"writing {dataset_id}", unit="episode", disable=not progress),
                    **kwargs)
            else:  # Minari writes metadata.json for an empty dataset, botorl the episodes
                mds = minari.create_dataset_from_buffers(dataset_id, [], **kwargs)
                eps, steps = _write_episodes_h5(dataset, mds.storage.data_path / "main_data.hdf5", progress, dataset_id)
                extra.update(total_episodes=eps, total_steps=steps)
            extra["dataset_size"] = mds.storage.get_size()
            mds.storage.update_metadata(extra)
        _write_flat(dataset, tmp_root / dataset_id / FLAT_FILE, meta)
        # Carry Minari's namespace marker files over if the destination has none.
        for ns in Path(dataset_id).parents[:-1]:
            src, dst = tmp_root / ns / "namespace_metadata.json", root_p / ns / "namespace_metadata.json"
            if src.exists() and not dst.exists():
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(src, dst)
        final.parent.mkdir(parents=True, exist_ok=True)
        if final.exists():  # overwrite: move the old one aside first, delete it after
            os.replace(final, tmp_root / "old")
        os.replace(tmp_root / dataset_id, final)
    finally:
        shutil.rmtree(tmp_root, ignore_errors=True)
    return final


def _write_flat(ds: Dataset, path: Path, meta: dict) -> None:
    """The flat copy, with the size and sha256 of its source ``data/main_data.hdf5`` and a checksum
    of its own rows, written atomically."""
    arrays = {**{k: getattr(ds, k) for k in FLAT_FIELDS}, "raw_action_max": np.asarray(ds.raw_action_max),
              "botorl_metadata": np.asarray(json.dumps(meta, default=_json_default)),
              **{f"infos/{k}": v for k, v in ds.infos.items()}}
    source = Path(path).parent / "data" / "main_data.hdf5"
    check = {"content_sha256": np.asarray(_content_sha256(arrays))}
    if source.exists():
        check.update(source_size=np.asarray(source.stat().st_size, np.int64),
                     source_sha256=np.asarray(file_sha256(source, data_cap())))
    buf = io.BytesIO()
    np.savez(buf, **arrays, **check)
    atomic_write_bytes(path, buf.getvalue())


_CHECK_KEYS = ("content_sha256", "source_size", "source_sha256")


def read_flat(folder: Path) -> Dataset | None:
    """The flat copy beside a botorl Minari dataset (None if there is none), trusted only if its
    source's size and sha256, its rows' checksum and its action range match the recorded ones
    (else ``FlatCacheInvalid`` naming the failed check)."""
    folder = Path(folder)
    path = folder / FLAT_FILE
    if not path.exists():
        return None
    source = folder / "data" / "main_data.hdf5"
    if source.exists():
        regular_file(source, "Minari data file")  # its sha256 is read below: a FIFO would hang
    try:
        check_npz(path)
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as err:
        raise FlatCacheInvalid(f"{path} cannot be read ({type(err).__name__}: {err})") from None
    if any(k not in arrays for k in _CHECK_KEYS):
        raise FlatCacheInvalid(f"{path} was written without checksums of its source (an older botorl)")
    if not source.exists():
        raise FlatCacheInvalid(f"{path}: its source {source} is missing")
    if int(arrays["source_size"]) != source.stat().st_size or str(arrays["source_sha256"]) != file_sha256(source, data_cap()):
        raise FlatCacheInvalid(f"{path} was made from a different {source} (size or sha256 differ)")
    body = {k: v for k, v in arrays.items() if k not in _CHECK_KEYS}
    if _content_sha256(body) != str(arrays["content_sha256"]):
        raise FlatCacheInvalid(f"{path}: its rows do not match their recorded sha256 (the file was changed)")
    act = body["actions"]
    raw = float(body["raw_action_max"])
    amax = float(np.abs(act).max()) if act.size else 0.0
    if abs(amax - min(raw, ACTION_CLIP)) > 1e-6:
        raise FlatCacheInvalid(f"{path}: stored actions reach {amax:.6g}, but the recorded action range is {raw:.6g}")
    infos = {k[6:]: v for k, v in body.items() if k.startswith("infos/")}
    meta = {"source": str(folder), "format": "minari", "botorl": json.loads(str(body["botorl_metadata"]))}
    return Dataset(**{k: body[k] for k in FLAT_FIELDS}, infos=infos, metadata=meta, raw_action_max=raw)


def rebuild_flat(ds: Dataset, folder: Path) -> None:
    """Rewrite the flat copy of the Minari dataset in ``folder`` from ``ds`` (read from the source)."""
    with contextlib.suppress(OSError):  # a read-only dataset folder: the Minari data are used each time
        _write_flat(ds, Path(folder) / FLAT_FILE, dict(ds.metadata.get("botorl") or {}))


def _json_default(obj):
    return obj.tolist() if isinstance(obj, (np.integer, np.floating, np.ndarray)) else str(obj)

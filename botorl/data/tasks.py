"""A task's offline data: read (or made) where its ``TaskSpec.dataset_source`` says."""

from __future__ import annotations

import os
from pathlib import Path

from botorl.data import loaders
from botorl.data.dataset import Dataset
from botorl.data.generate import cached_datasets, ensure_dataset
from botorl.data.user import load_task_data as load_user_data


def load_task_data(spec, path: str | os.PathLike | None = None, *, action_tolerance: float = 1e-3,
                   **kwargs) -> Dataset:
    """The task's offline data with raw rewards (the pipeline applies the transform).

    ``path`` (default: where the task's source says; the Cal-QL pickles must be named: a folder
    or ``expert.npy,bc.npy``) overrides the source. ``kwargs`` go to ``ensure_dataset``
    (generated tasks) or the user-task loader.
    """
    src = spec.dataset_source
    if src.kind == "user":  # a user's own task (botorl/data/user.py)
        return load_user_data(spec, path, **kwargs)
    if src.kind == "minari":
        return loaders.load_minari(
            path or src.ref, obs_keys=src.obs_keys, obs_dim=spec.obs_dim, action_dim=spec.action_dim,
            action_tolerance=action_tolerance)
    if src.kind == "calql_npy":
        if path is None:
            raise loaders.dataset_not_found(spec.name, [], None)
        p = Path(path).expanduser()
        if "," in str(path):
            expert, bc = (Path(part).expanduser() for part in str(path).split(",", 1))
        elif p.is_dir():
            expert, bc = (p / name for name in src.ref.split(","))
        else:
            expert, bc = p, None
        return loaders.load_calql_adroit(expert, bc, obs_dim=spec.obs_dim, action_dim=spec.action_dim)
    if path is not None:
        return loaders.load_minari(Path(path), obs_dim=spec.obs_dim, action_dim=spec.action_dim,
                                   action_tolerance=action_tolerance)
    return ensure_dataset(spec.name, **kwargs)


def data_status(spec) -> tuple[str, str]:
    """("found" | "generated-cached" | "missing" | "generate", a one-line detail)."""
    src = spec.dataset_source
    if src.kind == "user":
        return "found", src.ref or "in memory (botorl.register_task)"
    if src.kind == "minari":
        folder = loaders.minari_root() / src.ref
        if (folder / "data").is_dir():
            return "found", str(folder)
        return "missing", loaders.download_hint(spec.name)
    if src.kind == "calql_npy":
        return "missing", "pass --data.path: " + loaders.download_hint(spec.name)
    cached = cached_datasets(spec.name)
    if cached:
        return "generated-cached", str(cached[0])
    return "generate", f"made on first use, or now with `botorl data generate {spec.name}`"

"""The cache of generated datasets: ``ensure_dataset(task, steps, seed)``, Minari datasets under
``$BOTORL_DATA_DIR`` (a Minari root; docs/tasks.md) with id ``botorl/<task>/steps<steps>-seed<seed>-v0``.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from botorl.data import minari_io  # write_minari looked up when called: the tests replace it
from botorl.data.dataset import Dataset
from botorl.data.generators import DEFAULT_STEPS, GENERATORS, get_generator
from botorl.data.loaders import load_minari
from botorl.envs.registry import get_task
from botorl.errors import BotorlError, ConfigError


def data_dir() -> Path:
    """``$BOTORL_DATA_DIR`` or ``~/.botorl/datasets``."""
    env = os.environ.get("BOTORL_DATA_DIR")
    return Path(env).expanduser() if env else Path.home() / ".botorl" / "datasets"


def cache_id(task: str, steps: int, seed: int) -> str:
    return f"botorl/{task}/steps{int(steps)}-seed{int(seed)}-v0"


def cache_path(task: str, steps: int, seed: int) -> Path:
    return data_dir() / cache_id(task, steps, seed)


def _complete(path: Path) -> bool:
    return (path / "data" / "metadata.json").exists() and (path / "data" / "main_data.hdf5").exists()


def cached_datasets(task: str, steps: int | None = None, seed: int | None = None) -> list[Path]:
    """Folders of the cached datasets of ``task`` (largest first, then by seed), only those of
    ``steps`` / ``seed`` when given."""
    found = []
    for p in (data_dir() / "botorl" / task).glob("*"):  # nothing when the folder is missing
        m = re.fullmatch(r"steps(\d+)-seed(\d+)-v0", p.name)
        if m and _complete(p) and steps in (None, int(m.group(1))) and seed in (None, int(m.group(2))):
            found.append((-int(m.group(1)), int(m.group(2)), p))
    return [p for *_, p in sorted(found)]


def ensure_dataset(task: str, steps: int | None = None, seed: int = 0, *, progress: bool = True,
                   regenerate: bool = False) -> Dataset:
    """The generated dataset of ``task`` for (steps, seed; None: ``DEFAULT_STEPS``), from the cache
    or made and cached (deterministic for a seed, so a cache hit equals a fresh generation)."""
    if steps is None and task not in DEFAULT_STEPS:
        raise ConfigError(f"no default size for {task!r}; pass steps explicitly.")
    steps = DEFAULT_STEPS[task] if steps is None else int(steps)
    if steps <= 0:
        raise ConfigError(f"steps must be positive, got {steps}")
    path = cache_path(task, steps, seed)
    if _complete(path) and not regenerate:
        # the action range is the caller's to judge (load_offline: the task's data.action_tolerance;
        # the door demos reach |a| = 1.37), as it is for freshly generated data
        return load_minari(path, action_tolerance=float("inf"))
    ds = get_generator(task)(steps, seed, progress=progress)
    meta = {"task": task, "steps": steps, "seed": int(seed), "generator": GENERATORS[task]}
    try:
        minari_io.write_minari(ds, cache_id(task, steps, seed), root=data_dir(), overwrite=regenerate, metadata=meta,
                     description=f"botorl generated data for {task} ({steps} steps, seed {seed})",
                     progress=progress, env_spec=get_task(task).gym_spec())
    except (BotorlError, OSError):
        if not _complete(path):  # not a concurrent writer that finished first
            raise
    ds.metadata.update(cache_path=str(path))
    return ds

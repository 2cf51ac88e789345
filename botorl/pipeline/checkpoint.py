"""Run checkpoints: one folder per checkpoint, written whole or not at all.

    checkpoints/latest.json               {"name": ..., "stage": ..., "step": ..., "stage_done": ...}
    checkpoints/<stage>-final/            written at the end of each stage (kept)
    checkpoints/<stage>-step000012000/    every N steps inside a long stage (only the newest kept)
        agent.ckpt                        botorl.agents.checkpoint.save (bit-identical restore)
        <name>.npz                        arrays: replay buffer state_dict, D_warmup, ...
        state.json                        stage, step, numpy rng state, counters, stage_seconds

A checkpoint folder is first written as ``.tmp-*`` and then renamed (atomic on one file
system); ``latest.json`` is replaced atomically after the rename. A kill -9 at any moment
leaves ``latest.json`` pointing at a complete folder, so ``botorl resume`` loses at most the
steps since that checkpoint.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any, Callable

import numpy as np

from botorl.pipeline.rundir import atomic_write_json, read_json

LATEST = "latest.json"


def checkpoint_name(stage: str, step: int | None) -> str:
    return f"{stage}-final" if step is None else f"{stage}-step{int(step):09d}"


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _save_npz(path: Path, arrays: dict[str, Any]) -> None:
    flat = {}
    for k, v in arrays.items():
        if v is None:
            continue
        flat[k] = np.asarray(v)
    with open(path, "wb") as f:
        np.savez(f, **flat)
        f.flush()
        os.fsync(f.fileno())


def load_npz(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


class CheckpointManager:
    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)

    # ------------------------------------------------------------------ writing
    def save(
        self,
        name: str,
        *,
        state: dict[str, Any],
        agent: Any = None,
        save_agent: Callable[[str, Any], None] | None = None,
        arrays: dict[str, dict[str, Any]] | None = None,
    ) -> Path:
        tmp = self.root / f".tmp-{name}-{os.getpid()}"
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir(parents=True)
        if agent is not None:
            assert save_agent is not None
            save_agent(str(tmp / "agent.ckpt"), agent)
        for key, group in (arrays or {}).items():
            _save_npz(tmp / f"{key}.npz", group)
        atomic_write_json(tmp / "state.json", state)
        _fsync_dir(tmp)
        final = self.root / name
        if final.exists():  # re-saving the same name (e.g. after a resume): swap, then remove
            trash = self.root / f".trash-{name}-{os.getpid()}"
            if trash.exists():
                shutil.rmtree(trash)
            os.replace(final, trash)
            os.replace(tmp, final)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            os.replace(tmp, final)
        _fsync_dir(self.root)
        atomic_write_json(
            self.root / LATEST,
            {"name": name, "stage": state.get("stage"), "step": state.get("step"),
             "stage_done": bool(state.get("stage_done", False))},
        )
        self._prune(keep=name)
        return final

    def _prune(self, keep: str) -> None:
        """Intermediate (``-step``) checkpoints other than the newest are removed."""
        for p in self.root.iterdir():
            if p.name.startswith(".tmp-") or p.name.startswith(".trash-"):
                # left by a killed writer of *another* process; ours was renamed already
                if not p.name.endswith(f"-{os.getpid()}"):
                    shutil.rmtree(p, ignore_errors=True)
                continue
            if p.is_dir() and "-step" in p.name and p.name != keep:
                shutil.rmtree(p, ignore_errors=True)

    # ------------------------------------------------------------------ reading
    def latest(self) -> dict[str, Any] | None:
        p = self.root / LATEST
        if not p.exists():
            return None
        info = read_json(p)
        if not (self.root / info["name"]).is_dir():
            return None
        return info

    def path(self, name: str) -> Path:
        return self.root / name

    def exists(self, name: str) -> bool:
        return (self.root / name / "state.json").exists()

    def state(self, name: str) -> dict[str, Any]:
        return read_json(self.root / name / "state.json")

    def arrays(self, name: str, key: str) -> dict[str, np.ndarray] | None:
        p = self.root / name / f"{key}.npz"
        return load_npz(p) if p.exists() else None

"""Run checkpoints: one folder per checkpoint (``<stage>-final``, ``<stage>-step<N>``; files:
docs/CONTRACTS.md "Runs"), written whole or not at all.

A folder is written as ``.tmp-*`` and renamed into place, then ``latest.json`` is replaced, so
a kill -9 at any moment leaves ``latest.json`` pointing at a complete folder. Every file is
checked against the folder's ``MANIFEST.json`` (sizes, sha256, a sequence number) before it is
read; ``latest()`` falls back to the newest checkpoint that passes. The two newest step
checkpoints and every ``-final`` are kept. Checkpoints without a manifest (older botorl) are
accepted unverified.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import stat
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from botorl.data.minari_io import minari_root
from botorl.data.safe import check_npz, data_files, fingerprint, machine_memory
from botorl.errors import ConfigError, DataFormatError, warn
from botorl.io import atomic_write_json, file_sha256, open_regular, own_folder, read_json_object
from botorl.pipeline import faults
from botorl.pipeline.rundir import read_json

LATEST = "latest.json"
MANIFEST = "MANIFEST.json"


def file_limit() -> int:
    """Bytes one checkpoint file may hold: what it restores goes into memory, so at most this
    machine's (else 64 GiB); a larger file is refused before it is hashed."""
    return machine_memory() or 1 << 36


_DATA_SEEN: dict[tuple, dict] = {}


def data_identity(path: str | None) -> dict:
    """The fingerprint of a run's data (``data.path``: size and sha256 of what it reads, see
    ``botorl.data.safe.fingerprint``): every checkpoint of a run records what it started from, and
    a resume compares what is there now. Hashed once per process while the files' size, time and
    inode stay the same (a run saves many checkpoints)."""
    key: tuple = (path,)
    if path is not None:
        with contextlib.suppress(OSError):
            key += tuple((str(f), *(lambda st: (st.st_size, st.st_mtime_ns, st.st_ino, st.st_mode))(os.stat(f)))
                         for f in data_files(path, minari_root()))
    if key not in _DATA_SEEN:
        _DATA_SEEN[key] = fingerprint(path, minari_root())
    return _DATA_SEEN[key]


def full_identity(cfg) -> dict[str, Any]:
    """``run_identity`` with the data's fingerprint: what a checkpoint records and what the
    commands that read the data (resume, eval) check."""
    from botorl.configs.schema import run_identity  # lazy: JAX (through the configs' schema); botorl.api imports this module

    return {**run_identity(cfg), "data": data_identity(cfg.data.path)}


def check_identity(state: dict[str, Any], expected: list[dict[str, Any]], where: Path, name: str) -> None:
    """ConfigError (exit 2) naming both sides unless checkpoint ``name`` was written by the
    run(s) whose ``run_identity``s are ``expected`` (a checkpoint copied from another run, a
    config.json edited since, the data changed since: ``full_identity``); one that records no
    identity (older botorl) only warns, and so does one that records no data fingerprint when
    ``expected`` has one. Where ``expected`` has none (export, load_policy: the data are not
    read), the checkpoint's is not compared."""
    got = state.get("identity")
    if got is None:
        warn(f"checkpoint {name} in {where} records no run identity (written before checkpoints "
             f"recorded their run); it is taken to belong to this run's config.json.")
        return
    if isinstance(got, list) and all(isinstance(g, dict) for g in got):
        if not all("data" in e for e in expected):
            got = [{k: v for k, v in g.items() if k != "data"} for g in got]
        elif not all("data" in g for g in got):
            warn(f"checkpoint {name} in {where} records no fingerprint of its data (written before "
                 f"checkpoints recorded one); the data are taken to be the ones it was trained on.")
            expected = [{k: v for k, v in e.items() if k != "data"} for e in expected]
    if got == expected:
        return
    if not isinstance(got, list) or len(got) != len(expected) or not all(isinstance(g, dict) for g in got):
        diff = f"it records {got!r}, this run is {expected!r}"
    else:
        parts = []
        for i, (g, e) in enumerate(zip(got, expected)):
            keys = [k for k in sorted(set(g) | set(e)) if g.get(k) != e.get(k)]
            who = f"member {i}: " if len(expected) > 1 else ""
            parts += [f"{who}{k} {g.get(k)!r} in the checkpoint, {e.get(k)!r} in the config" if k != "data" else
                      f"{who}data {g.get(k)!r} in the checkpoint, {e.get(k)!r} now (the data changed since the run "
                      f"started, or config.json names other data)" for k in keys]
        diff = "; ".join(parts)
    raise ConfigError(
        f"checkpoint {name} in {where} belongs to another run ({diff}; 'pretraining' and 'config' are digests of the "
        f"settings that shape the saved state). A checkpoint is read only by the run that wrote it, with the data it "
        f"was trained on: put back that run's config.json and data, or start this one afresh with `botorl run` and "
        f"another --out."
    )


class CheckpointCorrupt(DataFormatError):
    """A checkpoint's file does not match its manifest (or cannot be read)."""


def checkpoint_name(stage: str, step: int | None) -> str:
    return f"{stage}-final" if step is None else f"{stage}-step{int(step):09d}"


def checkpoint_step(cfg, state: dict) -> int | None:
    """The step of a checkpoint within its stage (a stage-final one's: the stage's budget)."""
    step = state.get("step")
    if step is None and state.get("stage_done"):
        step = {"pretrain": cfg.offline.steps, "warmup": cfg.warmup.steps, "boto": cfg.boto.boto_steps,
                "finetune": cfg.online.steps}.get(state.get("stage"))
    return None if step is None else int(step)


def _fsync_dir(path: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def load_npz(path: Path) -> dict[str, np.ndarray]:
    try:
        check_npz(path)  # every member sized from its header before any is inflated
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as err:  # truncated zip, bad header, object arrays
        raise CheckpointCorrupt(
            f"{path} cannot be read ({type(err).__name__}: {err}); the checkpoint is damaged."
        ) from None


def _info(name: str, state: dict[str, Any]) -> dict[str, Any]:
    """What latest.json says of checkpoint ``name`` (and ``latest()`` returns)."""
    return {"name": name, "stage": state.get("stage"), "step": state.get("step"),
            "stage_done": bool(state.get("stage_done", False))}


class CheckpointManager:
    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        # the run directory (``RunDir.checkpoints``' parent): a checkpoints folder that is a link
        # would take every checkpoint, and latest.json's repair, outside it (io.own_folder)
        self.run_root = self.root.parent
        own_folder(self.run_root, self.root)

    def save(self, name: str, *, state: dict[str, Any], agent: Any = None,
             save_agent: Callable[[str, Any], None] | None = None, arrays: dict[str, dict[str, Any]] | None = None,
             documents: dict[str, Any] | None = None) -> Path:
        tmp = self.root / f".tmp-{name}-{os.getpid()}"
        if tmp.is_symlink():  # rmtree refuses a link (and so follows nothing); the link alone goes
            tmp.unlink()
        shutil.rmtree(tmp, ignore_errors=True)
        own_folder(self.run_root, tmp)
        if agent is not None:
            assert save_agent is not None
            save_agent(str(tmp / "agent.ckpt"), agent)
        faults.checkpoint(name, "files")
        for key, group in (arrays or {}).items():
            with os.fdopen(open_regular(tmp / f"{key}.npz", os.O_WRONLY | os.O_CREAT | os.O_EXCL), "wb") as f:
                np.savez(f, **{k: np.asarray(v) for k, v in group.items() if v is not None})
                f.flush()
                os.fsync(f.fileno())
        for key, doc in (documents or {}).items():  # "state" and "MANIFEST" are the checkpoint's own
            # plain json (NaN / Infinity kept as such: an env's state must come back exactly)
            atomic_write_json(tmp / f"{key}.json", doc, indent=None, exact=True, root=self.run_root)
        atomic_write_json(tmp / "state.json", state, root=self.run_root)
        files = {q.name: {"size": q.stat().st_size, "sha256": file_sha256(q, file_limit())} for q in sorted(tmp.iterdir())
                 if q.is_file() and not q.name.startswith(".")}
        seq = int(max([0.0, *(self.order(n)[0] for n in self.names())])) + 1  # after every checkpoint's
        atomic_write_json(tmp / MANIFEST, {"name": name, "seq": seq, "time": time.time(), "files": files},
                          root=self.run_root)
        _fsync_dir(tmp)
        final, trash = self.root / name, self.root / f".trash-{name}-{os.getpid()}"
        if final.exists():  # re-saving the same name (e.g. after a resume): swap, then remove
            shutil.rmtree(trash, ignore_errors=True)
            os.replace(final, trash)
        os.replace(tmp, final)
        shutil.rmtree(trash, ignore_errors=True)
        _fsync_dir(self.root)
        faults.checkpoint(name, "renamed")
        previous = self._latest_name()
        atomic_write_json(self.root / LATEST, _info(name, state), root=self.run_root)
        self._prune(keep={name, previous} - {None})
        return final

    def _latest_name(self) -> str | None:
        info = read_json_object(self.root / LATEST) or {}  # unreadable: none
        return str(info["name"]) if info.get("name") else None

    def _manifest(self, name: str) -> dict[str, Any] | None:
        p = self.root / name / MANIFEST
        if not p.exists():
            return None
        try:
            m = read_json(p)
            if not isinstance(m, dict) or not isinstance(m.get("files"), dict):
                raise ValueError("no file list")
            return m
        except (OSError, ValueError) as err:
            raise CheckpointCorrupt(f"checkpoint {name}: {MANIFEST} cannot be read ({err}).") from None

    def _prune(self, keep: set[str]) -> None:
        """Remove ``-step`` checkpoints other than ``keep`` (the newest and the one before it)."""
        for p in self.root.iterdir():
            if p.name.startswith(".tmp-") or p.name.startswith(".trash-"):
                # left by a killed writer of *another* process; ours was renamed already
                if not p.name.endswith(f"-{os.getpid()}"):
                    shutil.rmtree(p, ignore_errors=True)
                continue
            if p.is_dir() and "-step" in p.name and p.name not in keep:
                shutil.rmtree(p, ignore_errors=True)

    def names(self) -> list[str]:
        if not self.root.is_dir():
            return []
        # a link is not a checkpoint of this run, whatever it points at
        return sorted(p.name for p in self.root.iterdir()
                      if p.is_dir() and not p.is_symlink() and not p.name.startswith("."))

    def file(self, name: str, fname: str) -> Path:
        """The path of ``fname`` in checkpoint ``name``; CheckpointCorrupt unless it matches the
        manifest (no manifest: accepted)."""
        m = self._manifest(name)
        if Path(fname).name != fname or fname in ("", ".", ".."):
            raise CheckpointCorrupt(f"checkpoint {name}: {MANIFEST} lists {fname!r}, which is not a file of the folder.")
        path = self.root / name / fname
        if os.path.lexists(path) and not stat.S_ISREG(os.lstat(path).st_mode):  # a link, FIFO or device: never opened
            raise CheckpointCorrupt(f"checkpoint {name}: {fname} is not a regular file.")
        if m is None:
            return path
        want = m["files"].get(fname)
        if want is None:
            raise CheckpointCorrupt(f"checkpoint {name}: {fname} is not in its {MANIFEST}.")
        if not path.is_file():
            raise CheckpointCorrupt(f"checkpoint {name}: {fname} is missing.")
        size = path.stat().st_size
        if size != want.get("size"):
            raise CheckpointCorrupt(f"checkpoint {name}: {fname} has {size} bytes, its manifest says {want.get('size')}.")
        try:
            digest = file_sha256(path, file_limit())
        except ValueError as err:
            raise CheckpointCorrupt(f"checkpoint {name}: {err}; it is no checkpoint botorl wrote.") from None
        if digest != want.get("sha256"):
            raise CheckpointCorrupt(f"checkpoint {name}: {fname} does not match its sha256 checksum (the file changed "
                                    f"after it was written).")
        return path

    def verify(self, name: str) -> str | None:
        """None if checkpoint ``name`` passes the check, else the reason it does not."""
        folder = self.root / name
        if not (folder / "state.json").is_file():
            return f"checkpoint {name}: no state.json (not a complete checkpoint)"
        try:
            m = self._manifest(name)
            for fname in (m["files"] if m is not None else ["state.json"]):
                self.file(name, fname)
            st = read_json(folder / "state.json")
            if not isinstance(st, dict) or "stage" not in st:
                raise CheckpointCorrupt(f"checkpoint {name}: state.json has no stage.")
        except CheckpointCorrupt as err:
            return str(err)
        except (OSError, ValueError) as err:
            return f"checkpoint {name}: state.json cannot be read ({err})"
        return None

    def usable(self, name: str) -> bool:
        """Whether a resume from ``name`` can read everything it needs: it and every stage-final
        checkpoint it builds on pass the check (one without a manifest: its arrays load)."""
        def whole(n: str) -> bool:
            if self.verify(n) is not None:
                return False
            if self._manifest(n) is None:  # unverifiable: read its arrays
                try:
                    for p in (self.root / n).glob("*.npz"):
                        load_npz(self.file(n, p.name))
                except CheckpointCorrupt:
                    return False
            return True

        if not whole(name):
            return False
        try:
            done = self.state(name).get("done_stages") or []
        except CheckpointCorrupt:
            return False
        return all(whole(checkpoint_name(s, None)) for s in done if isinstance(s, str)
                   and checkpoint_name(s, None) != name)

    def verify_named(self, name: str) -> None:
        """ConfigError unless ``name`` is a checkpoint of this run that passes the check."""
        if name not in self.names() or not self.exists(name):
            raise ConfigError(f"checkpoint {name!r} is not in {self.root}; there are: {', '.join(self.names()) or 'none'}.")
        reason = self.verify(name)
        if reason is not None:
            good = [n for n in self.names() if n != name and self.verify(n) is None]
            raise ConfigError(f"{reason} Pick another: {', '.join(good) or 'none passes the check'}.")

    def chosen(self, name: str | None) -> str:
        """``name`` (checked: ``verify_named``), else the latest checkpoint."""
        if name is not None:
            self.verify_named(name)
            return name
        latest = self.latest()
        if latest is None:
            raise ConfigError(f"{self.root.parent} has no checkpoint that passes its check yet; wait for the first "
                              f"stage to finish, or name a checkpoint.")
        return latest["name"]

    def select(self, name: str) -> dict[str, Any]:
        """Make checkpoint ``name`` the one ``latest()`` returns (``botorl resume --from NAME``)."""
        self.verify_named(name)
        atomic_write_json(self.root / LATEST, _info(name, self.state(name)), root=self.run_root)
        return self.latest()

    def order(self, name: str) -> tuple[float, float]:
        """Sort key of checkpoint ``name``: newest last."""
        try:
            m = self._manifest(name)
        except CheckpointCorrupt:
            m = None
        if m is not None:
            return (float(m.get("seq", 0)), float(m.get("time", 0)))
        try:  # written before manifests: by its time
            return (0.0, float(read_json(self.root / name / "state.json").get("time", 0)))
        except (OSError, ValueError, AttributeError, TypeError):
            return (-1.0, 0.0)

    def latest(self) -> dict[str, Any] | None:
        """The checkpoint a resume starts from: latest.json's if verified, else the newest verified
        one (the failures named on stderr, latest.json pointed at it); None if none passes."""
        p = self.root / LATEST
        named, names = self._latest_name(), self.names()
        bad: list[str] = []
        if named is None and p.exists():
            bad.append(f"{p} cannot be read")
        elif named is not None and named not in names:  # also refuses "../elsewhere": only this run's
            bad.append(f"{p} names {named}, which does not exist")
        others = sorted((n for n in names if n != named), key=self.order, reverse=True)
        for name in ([named] if named in names else []) + others:
            reason = self.verify(name)
            if reason is not None:
                bad.append(reason)
                continue
            if bad:
                warn(f"{'; '.join(bad)}. Falling back to the previous checkpoint, {name}.")
                with contextlib.suppress(OSError):  # a read-only run directory (eval): nothing to repair
                    atomic_write_json(self.root / LATEST, _info(name, self.state(name)), root=self.run_root)
            return _info(name, self.state(name))
        if bad:
            warn(f"{'; '.join(bad)}; no checkpoint passes the check.")
        return None

    def exists(self, name: str) -> bool:
        return (self.root / name / "state.json").exists()

    def state(self, name: str) -> dict[str, Any]:
        path = self.file(name, "state.json")
        try:
            st = read_json(path)
        except (OSError, ValueError) as err:
            raise CheckpointCorrupt(f"checkpoint {name}: {path} cannot be read ({err}). Resume from an earlier "
                                    f"one with `botorl resume RUN_DIR --from NAME` (there are: {', '.join(self.names())}).") from None
        if not isinstance(st, dict):
            raise CheckpointCorrupt(f"checkpoint {name}: {path} does not hold a state object.")
        return st

    def document(self, name: str, key: str) -> Any:
        """The JSON document ``key`` of checkpoint ``name`` (checked), or None if it has none."""
        p = self.root / name / f"{key}.json"
        if not p.exists():
            return None
        try:
            return read_json(self.file(name, p.name))
        except (OSError, ValueError) as err:
            raise CheckpointCorrupt(f"checkpoint {name}: {p} cannot be read ({err}). Resume from an earlier "
                                    f"one with `botorl resume RUN_DIR --from NAME`.") from None

    def arrays(self, name: str, key: str) -> dict[str, np.ndarray] | None:
        p = self.root / name / f"{key}.npz"
        return load_npz(self.file(name, p.name)) if p.exists() else None


def resume_point(ckpt: CheckpointManager, member_cfgs: list, resume: bool):
    """(the newest checkpoint, {done_stages, stage_seconds}, failed members, the mid-stage point or None)."""
    latest = ckpt.latest() if resume else None
    if latest is None:
        return None, {"done_stages": [], "stage_seconds": {}}, {}, None
    st = ckpt.state(latest["name"])
    check_identity(st, [full_identity(c) for c in member_cfgs], ckpt.root, latest["name"])
    mid = None if st["stage_done"] else {"name": latest["name"], "stage": st["stage"], "step": st["step"]}
    return latest, {"done_stages": list(st["done_stages"]), "stage_seconds": dict(st["stage_seconds"])}, \
        st.get("failed") or {}, mid

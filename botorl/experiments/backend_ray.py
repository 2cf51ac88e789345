"""The sweep's Ray backend: one Ray task (num_cpus=1) per trial, on an existing cluster
(``--ray-address``) or a local instance in ``/tmp/botorl-ray-XXXXXXXX``, whose dir (path, device
and inode) and daemons (pid, start time and the sweep's token) sweep.json records so that the next
invocation cleans up after a SIGKILL (``cleanup_previous``; sweep.json is data: it stops and removes
only what ``backend_local.stop_recorded`` and ``own_ray_temp_dir`` accept, which a copied or crafted
sweep.json cannot name)."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import stat
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from botorl.errors import BotorlError
from botorl.experiments.backend_local import SINGLE_THREAD_ENV, TOKEN_ENV, carries_token, descendants, \
    folder_identity, process_record, spawn, stop_recorded, sweep_token, trial_env, usable_cores
from botorl.io import read_json_object

RAY_ENV_PREFIXES = ("BOTORL_", "XLA_", "JAX_", "MINARI_", "MUJOCO_", "PYTHONUNBUFFERED")

# A local instance's temp dir: short (Ray's unix sockets live under it, 108-byte limit), one
# level below /tmp, named by tempfile.mkdtemp.
RAY_TEMP_ROOT = "/tmp"
RAY_TEMP_PREFIX = "botorl-ray-"
_RAY_TEMP_NAME = re.compile(re.escape(RAY_TEMP_PREFIX) + r"[A-Za-z0-9_]{6,16}")
# Written inside a temp dir when this backend makes it: the identity of the sweep folder it serves.
# The dir is this user's alone (mkdtemp: mode 0700), so no file of a sweep folder can forge it.
RAY_TEMP_MARK = ".botorl-sweep.json"


def make_ray_temp_dir(out: str | os.PathLike) -> dict[str, Any]:
    """A new temp dir for a local Ray instance of the sweep of ``out``, marked as that sweep's; the
    record sweep.json keeps of it (path, device, inode)."""
    tmp = tempfile.mkdtemp(prefix=RAY_TEMP_PREFIX, dir=RAY_TEMP_ROOT)
    with open(os.path.join(tmp, RAY_TEMP_MARK), "x") as f:
        json.dump({"sweep": folder_identity(out)}, f)
    st = os.lstat(tmp)
    return {"path": tmp, "dev": st.st_dev, "ino": st.st_ino}


def own_ray_temp_dir(record: Any, out: str | os.PathLike) -> str | None:
    """The path of ``record`` (sweep.json's ``ray_local_temp_dir``) if it is a dir this backend
    made for the sweep of ``out``: a direct child of /tmp named ``botorl-ray-XXXXXXXX``, no ``..``
    or link on the way, a real directory owned by this user, of the recorded device and inode, whose
    mark names this sweep folder; else None."""
    if not isinstance(record, dict) or not isinstance(path := record.get("path"), str):
        return None
    parent, _, name = path.rpartition("/")
    if parent != RAY_TEMP_ROOT or not _RAY_TEMP_NAME.fullmatch(name):
        return None
    try:
        st = os.lstat(path)
    except OSError:
        return None
    mine = stat.S_ISDIR(st.st_mode) and st.st_uid == os.getuid() and (st.st_dev, st.st_ino) == (
        record.get("dev"), record.get("ino"))
    if not mine or os.path.realpath(path) != os.path.join(os.path.realpath(RAY_TEMP_ROOT), name):
        return None
    mark = read_json_object(Path(path) / RAY_TEMP_MARK)
    ident = folder_identity(out)
    return path if mark is not None and ident is not None and mark.get("sweep") == ident else None


def cleanup_previous(old_manifest: dict[str, Any], out: str | os.PathLike) -> None:
    """Stop the daemons of a local Ray instance that an earlier, killed sweep of ``out`` started
    (those it recorded, with their descendants) and remove its temp dir (if this backend made it
    for this sweep folder)."""
    stop_recorded(old_manifest.get("ray_local_processes"), out)
    tmp = own_ray_temp_dir(old_manifest.get("ray_local_temp_dir"), out)
    if tmp is not None:
        shutil.rmtree(tmp, ignore_errors=True)


class RayBackend:
    def __init__(self, sweep):
        self.sweep = sweep
        self.ray = None
        self.fn = None
        self.tmp: str | None = None

    def start(self, pending: int) -> int:
        """Connect to (or start) Ray; the number of trials to run at once."""
        opt = self.sweep.opt
        workers = max(1, int(opt.workers)) if opt.workers else len(usable_cores())
        if not pending:
            return 1
        try:
            import ray  # lazy: optional dependency (the ray extra)
        except ImportError:
            raise BotorlError(
                "The ray backend needs Ray, which is not installed. Install it with "
                "`pip install 'botorl[ray]'` (or `pip install 'ray[default]'`), or use "
                "--backend local."
            ) from None
        self.ray = ray
        kwargs: dict[str, Any] = {"log_to_driver": False, "include_dashboard": False}
        if opt.ray_address:
            kwargs["address"] = opt.ray_address
        else:
            kwargs["num_cpus"] = workers
            record = make_ray_temp_dir(self.sweep.out)
            self.tmp = kwargs["_temp_dir"] = record["path"]
            self.sweep.manifest["ray_local_temp_dir"] = record
            self.sweep.save()
        token = sweep_token(self.sweep.out)
        if not ray.is_initialized():
            # the local daemons inherit the token: what lets a later sweep stop them. Only while
            # ray.init starts them: left in this process's environment, every child it starts
            # afterwards (not the sweep's) would carry the token too
            before = os.environ.get(TOKEN_ENV)
            if self.tmp:
                os.environ[TOKEN_ENV] = token
            try:
                ray.init(**kwargs)
            except Exception as err:  # a bad --ray-address is the user's to fix
                raise BotorlError(
                    f"Could not connect to or start Ray ({kwargs.get('address', 'local instance')}): "
                    f"{err}. Check --ray-address (e.g. ray://host:10001 or auto) or leave it out "
                    "to start a local instance."
                ) from None
            finally:
                if before is None:
                    os.environ.pop(TOKEN_ENV, None)
                else:
                    os.environ[TOKEN_ENV] = before
            if self.tmp:  # the local instance's daemons: the processes ray.init started
                self.sweep.manifest["ray_local_processes"] = [
                    r for p in descendants([os.getpid()]) if carries_token(p, token)
                    and (r := process_record(p, token)) is not None]
                self.sweep.save()
        self.fn = ray.remote(num_cpus=1, max_retries=0)(_ray_trial)
        if opt.ray_address and not opt.workers:  # an existing cluster: as many trials at once as it has CPUs
            workers = max(1, int(ray.cluster_resources().get("CPU", 1)))
        return min(workers, pending)

    def launch(self, trial, slot: int | None) -> Any:
        sweep = self.sweep
        run_dir, cmd, log = sweep.prepare(trial)
        # only the settings that concern botorl: the rest of this machine's environment (PATH,
        # HOME) may be wrong on another node of a cluster
        env = {k: v for k, v in trial_env(sweep_token(sweep.out), True).items()
               if k in SINGLE_THREAD_ENV or k.startswith(RAY_ENV_PREFIXES)}
        return self.fn.remote(cmd, env, str(log), str(run_dir))

    def poll(self, running: dict) -> list[tuple[int, int]]:
        refs = {ref: k for k, (_, ref) in running.items()}
        if not refs:
            return []
        out = []
        ready, _ = self.ray.wait(list(refs), num_returns=len(refs), timeout=self.sweep.opt.poll_interval)
        for ref in ready:
            try:
                code = int(self.ray.get(ref))
            except Exception as err:  # the Ray task itself died (node lost, worker killed)
                print(f"botorl sweep: Ray task failed: {err}", file=sys.stderr)
                code = -1
            out.append((refs[ref], code))
        return out

    def abort(self, running: dict, signum: int = 15) -> None:
        for _, ref in running.values():
            with contextlib.suppress(Exception):
                self.ray.cancel(ref, force=True)

    def close(self) -> None:
        if self.ray is not None and self.ray.is_initialized():
            self.ray.shutdown()
        if self.tmp:
            cleanup_previous(self.sweep.manifest, self.sweep.out)  # its daemons and temp dir, as recorded in start
            self.tmp = None
            with contextlib.suppress(Exception):
                self.sweep.manifest.pop("ray_local_temp_dir", None)
                self.sweep.manifest.pop("ray_local_processes", None)
                self.sweep.save()


def _ray_trial(cmd: list[str], env: dict[str, str], log: str, run_dir: str) -> int:
    """Body of the Ray task: one trial as a subprocess of the Ray worker."""
    proc = spawn(cmd, log, run_dir, {**os.environ, **env}, cpu=None)
    try:
        return proc.wait()
    except BaseException:  # ray.cancel raises in the worker: do not leave the trial running
        proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
        raise

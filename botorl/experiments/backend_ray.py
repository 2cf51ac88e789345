"""The sweep's Ray backend: one Ray task (num_cpus=1) per trial, on an existing cluster
(``--ray-address``) or on a local instance the sweep starts and stops. A local instance
lives in a private temp dir named on every one of its processes' command lines, so a sweep
killed with SIGKILL has its leftover daemons stopped by the next invocation
(``cleanup_previous``)."""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from botorl.errors import BotorlError
from botorl.experiments.backend_local import SINGLE_THREAD_ENV, TRIAL_PID, stop_processes_mentioning, usable_cores
from botorl.experiments.child import launcher
from botorl.io import atomic_write_json

RAY_ENV_PREFIXES = ("BOTORL_", "XLA_", "JAX_", "MINARI_", "MUJOCO_", "PYTHONUNBUFFERED")


def cleanup_previous(old_manifest: dict[str, Any]) -> None:
    """Stop the daemons of a local Ray instance that an earlier, killed sweep started."""
    tmp = old_manifest.get("ray_local_temp_dir")
    if isinstance(tmp, str) and tmp.startswith("/tmp/botorl-ray-"):
        stop_processes_mentioning(tmp)
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
            import ray
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
            # Short path: Ray's unix sockets live under it (108-byte limit).
            self.tmp = tempfile.mkdtemp(prefix="botorl-ray-", dir="/tmp")
            kwargs["_temp_dir"] = self.tmp
            self.sweep.manifest["ray_local_temp_dir"] = self.tmp
            self.sweep.save()
        if not ray.is_initialized():
            try:
                ray.init(**kwargs)
            except Exception as err:  # a bad --ray-address is the user's to fix
                raise BotorlError(
                    f"Could not connect to or start Ray ({kwargs.get('address', 'local instance')}): "
                    f"{err}. Check --ray-address (e.g. ray://host:10001 or auto) or leave it out "
                    "to start a local instance."
                ) from None
        self.fn = ray.remote(num_cpus=1, max_retries=0)(_ray_trial)
        if opt.ray_address and not opt.workers:  # an existing cluster: as many trials at once as it has CPUs
            workers = max(1, int(ray.cluster_resources().get("CPU", 1)))
        return min(workers, pending)

    def launch(self, trial, slot: int | None) -> Any:
        sweep = self.sweep
        run_dir, cmd, log = sweep.prepare(trial)
        sweep.entry(trial).update(pid=None, cpu=None)
        sweep.save()
        # only the settings that concern botorl: the rest of this machine's environment (PATH,
        # HOME) may be wrong on another node of a cluster
        env = {k: v for k, v in sweep.trial_env().items() if k in SINGLE_THREAD_ENV or k.startswith(RAY_ENV_PREFIXES)}
        return self.fn.remote(cmd, env, str(log), str(run_dir), str(sweep.out))

    def poll(self, running: dict) -> list[tuple[int, int]]:
        refs = {r.handle: k for k, r in running.items()}
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
        for r in running.values():
            with contextlib.suppress(Exception):
                self.ray.cancel(r.handle, force=True)

    def close(self) -> None:
        if self.ray is not None and self.ray.is_initialized():
            self.ray.shutdown()
        if self.tmp:
            stop_processes_mentioning(self.tmp)
            shutil.rmtree(self.tmp, ignore_errors=True)
            self.tmp = None
            with contextlib.suppress(Exception):
                self.sweep.manifest.pop("ray_local_temp_dir", None)
                self.sweep.save()


def _ray_trial(cmd: list[str], env: dict[str, str], log: str, run_dir: str, cwd: str) -> int:
    """Body of the Ray task: one trial as a subprocess of the Ray worker."""
    full_env = dict(os.environ)
    full_env.update(env)
    with open(log, "ab") as logf:
        proc = subprocess.Popen(
            launcher(cmd, os.getpid()), stdout=logf, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            env=full_env, cwd=cwd,
        )
    atomic_write_json(Path(run_dir) / TRIAL_PID, {"pid": proc.pid, "host": socket.gethostname(), "cpu": None})
    try:
        return proc.wait()
    except BaseException:  # ray.cancel raises in the worker: do not leave the trial running
        proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
        raise

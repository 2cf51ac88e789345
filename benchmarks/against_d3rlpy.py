"""botorl's updates beside d3rlpy's on identical shapes, timed in the same rounds.

    python benchmarks/against_d3rlpy.py [--json out.json] [--threads 1] [--quick] [--only sac2,calql]

The options are `botorl bench`'s (``botorl.benchmarks.suite``, which times botorl's side).
This file and ``d3rlpy_worker.py`` live outside the package because d3rlpy 2.8.1 pins
gymnasium 1.0 and needs PyTorch, neither of which botorl has as a dependency: d3rlpy runs in
its own venv (default ``~/.cache/botorl/d3rlpy-venv``, ``BOTORL_D3RLPY_VENV`` to move it),
made on first use with ``python -m venv`` and pip. torch is pinned to the CPU build the
reference figures used (docs/performance.md): an unpinned ``torch`` would pull a multi-GB
CUDA build.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

from botorl.benchmarks.workloads import Workload
from botorl.errors import BotorlError

D3RLPY_VERSION = "2.8.1"
TORCH_VERSION = "2.13.0"
WORKER = Path(__file__).with_name("d3rlpy_worker.py")


def venv_dir() -> Path:
    default = Path.home() / ".cache" / "botorl" / "d3rlpy-venv"
    return Path(os.environ.get("BOTORL_D3RLPY_VENV", str(default))).expanduser()


def venv_python(venv: Path | None = None) -> Path:
    return (venv or venv_dir()) / "bin" / "python"


def _has_d3rlpy(python: Path) -> bool:
    if not python.exists():
        return False
    probe = subprocess.run([str(python), "-c", "import d3rlpy, torch"], capture_output=True)
    return probe.returncode == 0


def ensure_venv(venv: Path | None = None, log: Any = None) -> Path:
    """The venv's python, creating the venv and installing d3rlpy first if needed."""
    venv = venv or venv_dir()
    python = venv_python(venv)
    if _has_d3rlpy(python):
        return python
    log = log or sys.stderr
    print(f"botorl bench: making the d3rlpy venv in {venv} (once; a few minutes) ...", file=log)
    steps = [
        [sys.executable, "-m", "venv", str(venv)],
        [str(python), "-m", "pip", "install", "--quiet", f"torch=={TORCH_VERSION}", f"d3rlpy=={D3RLPY_VERSION}"],
    ]
    for cmd in steps:
        done = subprocess.run(cmd, capture_output=True, text=True)
        if done.returncode != 0:
            tail = (done.stderr or done.stdout).strip().splitlines()[-5:]
            raise BotorlError(
                f"Could not make the d3rlpy virtual environment in {venv}: `{' '.join(cmd)}` "
                f"failed ({' | '.join(tail)}). Check that pip can reach a package index with "
                f"d3rlpy=={D3RLPY_VERSION} and torch=={TORCH_VERSION}, or point "
                f"BOTORL_D3RLPY_VENV at a venv that has both, or run `botorl bench` (botorl alone).")
    if not _has_d3rlpy(python):
        raise BotorlError(f"The venv {venv} was made but `import d3rlpy, torch` fails in it; "
                          f"delete the folder and run again.")
    return python


def d3rlpy_spec(w: Workload) -> dict[str, Any]:
    """The worker's options for the d3rlpy update that matches ``w``."""
    return {
        "algo": w.d3rlpy_algo, "n_critics": w.num_critics, "critic_hidden": list(w.critic_hidden),
        "actor_hidden": list(w.actor_hidden), "obs_dim": w.obs_dim, "action_dim": w.action_dim, "batch": w.batch,
        "n_action_samples": w.n_action_samples, "utd": w.utd, "layer_norm": int(w.layer_norm),
    }


class D3rlpyWorker:
    """A long-lived ``d3rlpy_worker.py --serve`` subprocess (see that file for the protocol)."""

    def __init__(self, python: Path, threads: int = 0):
        env = dict(os.environ)
        env.pop("PYTHONPATH", None)  # the worker must not see botorl's site-packages
        if threads > 0:
            env["OMP_NUM_THREADS"] = str(threads)
        self.proc = subprocess.Popen(
            [str(python), str(WORKER), "--serve", "--threads", str(threads)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
            text=True, env=env)
        self.info = self._read()
        self.threads = threads

    def _read(self) -> dict[str, Any]:
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line:
            raise BotorlError("The d3rlpy worker exited without answering; run "
                              f"`{venv_python()} {WORKER} --algo sac` to see its error.")
        return json.loads(line)

    def request(self, **req: Any) -> dict[str, Any]:
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps(req) + "\n")
        self.proc.stdin.flush()
        return self._read()

    def setup(self, w: Workload) -> str | None:
        """Build a workload's d3rlpy twin; returns an error text instead of raising (the row shows it)."""
        spec = d3rlpy_spec(w)
        if self.threads > 0:
            spec["threads"] = self.threads
        answer = self.request(cmd="setup", name=w.name, spec=spec)
        return None if answer.get("ok") else str(answer.get("error"))

    def time(self, name: str, min_time: float) -> tuple[float, float]:
        """(updates per wall-clock second, updates per CPU second of the worker)."""
        answer = self.request(cmd="time", name=name, min_time=min_time)
        if not answer.get("ok"):
            raise RuntimeError(f"d3rlpy worker: {answer.get('error')}")
        return float(answer["updates_per_s"]), float(answer.get("updates_per_cpu_s", "nan"))

    def close(self) -> None:
        try:
            self.request(cmd="quit")
        except Exception:
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def main(argv: list[str] | None = None) -> int:
    from botorl.benchmarks.suite import main as bench_main

    return bench_main(argv, twin=lambda cfg: D3rlpyWorker(ensure_venv(), threads=cfg.threads),
                      prog="python benchmarks/against_d3rlpy.py")


if __name__ == "__main__":
    try:
        sys.exit(main())
    except BotorlError as err:  # as the CLI does: one paragraph, exit code 2
        print(f"against_d3rlpy: error: {err}", file=sys.stderr)
        sys.exit(err.exit_code)

"""Shared test fixtures. Each area's tests live in tests/test_<area>_*.py."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

# Tests must never reach the network or a user's datasets.
os.environ["MINARI_DATASETS_PATH"] = tempfile.mkdtemp(prefix="botorl-minari-")
os.environ["BOTORL_DATA_DIR"] = tempfile.mkdtemp(prefix="botorl-data-")
os.environ.setdefault("MUJOCO_GL", "egl")
# Two CPU devices on any machine, so the population tests exercise the split of members over
# devices (pipeline/population.py) whatever the core count; subprocess runs inherit it.
os.environ.setdefault("BOTORL_CPU_DEVICES", "2")

from botorl.jaxsetup import setup_jax  # noqa: E402

setup_jax()

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED = REPO_ROOT.parent / "shared"


@pytest.fixture(scope="session")
def door_demos_path() -> Path:
    """The 25 DAPG door demos shipped beside the project (../shared/data/adroit)."""
    path = SHARED / "data" / "adroit" / "door_human_demos.npz"
    if not path.exists():
        pytest.skip(f"{path} is not present")
    return path


def subprocess_env() -> dict[str, str]:
    """The environment of a botorl subprocess: this checkout first on the path."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO_ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def sigkill_in_finetune(cmd: list[str], out: Path, *, cwd=None, timeout: float = 600):
    """Start ``cmd`` (a `botorl run`), SIGKILL it as soon as ``out`` holds a mid-fine-tuning
    checkpoint, and return (the step it was killed at, the process). Fails the test when no
    such checkpoint appears; latest.json must never be read half-written (atomic writes)."""
    import json
    import signal
    import subprocess
    import time

    proc = subprocess.Popen(cmd, cwd=cwd, env=subprocess_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)
    latest = out / "checkpoints" / "latest.json"
    killed_at = None
    deadline = time.time() + timeout
    try:
        while time.time() < deadline and proc.poll() is None:
            if latest.exists():
                try:
                    info = json.loads(latest.read_text())
                except json.JSONDecodeError:
                    raise AssertionError("latest.json was read half-written") from None
                if info["stage"] == "finetune" and not info["stage_done"]:
                    os.kill(proc.pid, signal.SIGKILL)
                    killed_at = info["step"]
                    break
            time.sleep(0.02)
    finally:
        if proc.poll() is None and killed_at is None:
            os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    assert killed_at is not None, f"no mid-stage checkpoint appeared; stderr: {proc.stderr.read().decode()[-2000:]}"
    return killed_at, proc

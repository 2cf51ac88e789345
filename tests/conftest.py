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

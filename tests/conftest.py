"""Shared test fixtures and the environment every test runs in; the helpers tests share are in
helpers.py. Each area's tests live in tests/test_<area>_*.py."""

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
# devices (agents/population.py) whatever the core count; subprocess runs inherit it.
os.environ.setdefault("BOTORL_CPU_DEVICES", "2")

from botorl.jaxsetup import setup_jax  # noqa: E402

from helpers import REPO_ROOT  # noqa: E402

setup_jax()

SHARED = REPO_ROOT.parent / "shared"


@pytest.fixture(scope="session")
def door_demos_path() -> Path:
    """The 25 DAPG door demos shipped beside the project (../shared/data/adroit)."""
    path = SHARED / "data" / "adroit" / "door_human_demos.npz"
    if not path.exists():
        pytest.skip(f"{path} is not present")
    return path


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
    """Drop each test module's compiled programs when it ends. Every XLA CPU executable holds
    memory maps; one pytest process of the whole suite reached the kernel's limit
    (vm.max_map_count, 65,530) after ~440 tests and died with SIGSEGV inside libgcc's unwinder
    (the map count measured ~26k after the first 150 tests, ~2-6k per module with this). The
    persistent compilation cache makes the recompiles of the next module cheap."""
    yield
    import gc

    import jax

    jax.clear_caches()
    gc.collect()

"""A run on a 3 MB file system that fills up mid-run ends with exit 2 within a minute, naming the
directory, with TensorBoard on (its writer thread used to hang the process), and summary.json
says failed. Needs `unshare -m` and `mount -t tmpfs` (root in a container); skipped elsewhere.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

SCRIPT = r"""
set -e
mount -t tmpfs -o size=3m tmpfs "$D"
dd if=/dev/zero of="$D/ballast" bs=1k count=$((3 * 1024 - 120)) 2>/dev/null || true
set +e
"$PY" -m botorl.cli run --task pointmaze-umaze --profile smoke --no-progress --out "$D/run"
rc=$?
echo "@@summary"
cat "$D/run/summary.json" 2>/dev/null
exit $rc
"""


def _can_mount(tmp_path) -> bool:
    if shutil.which("unshare") is None or os.geteuid() != 0:
        return False
    d = tmp_path / "probe"
    d.mkdir()
    r = subprocess.run(["unshare", "-m", "sh", "-c", f"mount -t tmpfs -o size=64k tmpfs {d}"], capture_output=True)
    return r.returncode == 0


@pytest.mark.timeout(300)
def test_disk_full_mid_run_exits_2_quickly(tmp_path):
    if not _can_mount(tmp_path):
        pytest.skip("needs unshare -m and tmpfs mounts (root)")
    d = tmp_path / "small"
    d.mkdir()
    env = dict(os.environ, D=str(d), PY=sys.executable,
               PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    t0 = time.time()
    r = subprocess.run(["unshare", "-m", "sh", "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=240)
    elapsed = time.time() - t0
    assert r.returncode == 2, r.stderr[-3000:]
    assert "disk is full" in r.stderr and f"{d}/run" in r.stderr and "Traceback" not in r.stderr
    assert elapsed < 60 + 30  # a minute, plus the interpreter's and JAX's start on a loaded 2-core machine
    summary = r.stdout.split("@@summary", 1)[1].strip()
    assert summary, "summary.json was not written at all"
    s = json.loads(summary)
    assert s["status"] == "failed" and "disk is full" in s["error"]



def test_read_only_out_at_start_exits_2(tmp_path):
    """--out on a file system mounted read-only (EROFS): exit 2 naming the directory."""
    if not _can_mount(tmp_path):
        pytest.skip("needs unshare -m and tmpfs mounts (root)")
    d = tmp_path / "ro"
    d.mkdir()
    script = ('mount -t tmpfs -o ro,size=64k tmpfs "$D" && exec "$PY" -m botorl.cli run --task pointmaze-umaze '
              '--profile smoke --no-progress --out "$D/run"')
    env = dict(os.environ, D=str(d), PY=sys.executable,
               PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run(["unshare", "-m", "sh", "-c", script], env=env, capture_output=True, text=True, timeout=240)
    assert r.returncode == 2, r.stderr[-3000:]
    assert "read-only" in r.stderr and f"{d}/run" in r.stderr and "Traceback" not in r.stderr

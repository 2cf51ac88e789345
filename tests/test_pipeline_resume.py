"""A run killed with SIGKILL in the middle of a stage continues with `botorl resume DIR`.

The run is a subprocess (the real CLI). It is killed as soon as a mid-stage checkpoint of
fine-tuning exists (so the kill lands inside a stage, between checkpoints), then resumed to
the end. Checks: summary says finished; eval.csv and the metrics have each step once, in
order (rows written after the checkpoint and before the kill are dropped and redone); the
resumed run lost at most the steps since the checkpoint.
"""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import sigkill_in_finetune
from conftest import subprocess_env as _env



def _csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.timeout(600)
def test_sigkill_mid_stage_then_resume(tmp_path):
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "botorl.cli", "run", "--task", "pointmaze-umaze", "--profile", "smoke",
           "--no-progress", "--no-tensorboard", "--online.steps", "400", "--checkpoint_every", "50",
           "--eval.interval", "100", "--out", str(out)]
    killed_at, proc = sigkill_in_finetune(cmd, out, timeout=420)
    assert proc.returncode == -signal.SIGKILL
    assert json.loads((out / "summary.json").read_text())["status"] == "running"

    res = subprocess.run([sys.executable, "-m", "botorl.cli", "resume", str(out), "--no-progress"], env=_env(),
                         capture_output=True, text=True, timeout=420)
    assert res.returncode == 0, res.stderr[-3000:]
    assert f"resuming {out} from finetune step {killed_at}" in res.stderr

    s = json.loads((out / "summary.json").read_text())
    assert s["status"] == "finished"
    assert set(s["stage_seconds"]) == {"pretrain", "warmup", "boto", "finetune"}
    steps = [int(r["env_step"]) for r in _csv(out / "eval.csv")]
    # the warm-up's evaluation at 0, fine-tuning's when it starts (30, after the warm-up), then every 100
    assert steps == [0, 30, 100, 200, 300, 400]
    logged = [int(r["step"]) for r in _csv(out / "metrics" / "finetune.csv")]
    assert logged == sorted(set(logged)) and logged[-1] == 400
    jsonl = [json.loads(x)["step"] for x in (out / "metrics" / "finetune.jsonl").read_text().splitlines()]
    assert jsonl == logged
    # the stages before fine-tuning were not redone: one pre-training log ends at its last step
    pre = [int(r["step"]) for r in _csv(out / "metrics" / "pretrain.csv")]
    assert pre == sorted(set(pre))
    assert json.loads((out / "checkpoints" / "latest.json").read_text())["name"] == "finetune-final"

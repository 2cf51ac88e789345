"""MetricsLogger's optional sinks: TensorBoard events read back, and the W&B calls it makes."""

from __future__ import annotations

import struct

import pytest

from botorl.pipeline.rundir import MetricsLogger, RunDir


def _scalars(tb_dir):
    """(tag, step, value) of every scalar in the event files (TFRecord framing, Event protos)."""
    from tensorboardX.proto import event_pb2

    out = []
    for f in sorted(tb_dir.glob("events*")):
        data, i = f.read_bytes(), 0
        while i < len(data):
            (n,) = struct.unpack("<Q", data[i:i + 8])
            ev = event_pb2.Event()
            ev.ParseFromString(data[i + 12:i + 12 + n])
            i += 12 + n + 4
            out += [(v.tag, ev.step, v.simple_value) for v in ev.summary.value]
    return out


def test_tensorboard_events_hold_stage_and_eval_scalars(tmp_path):
    pytest.importorskip("tensorboardX")
    run = RunDir(tmp_path / "run")
    run.create()
    log = MetricsLogger(run, tensorboard=True)
    log.log("pretrain", 500, {"critic_loss": 2.5, "note": "text is not a scalar"})
    log.log_eval({"stage": "finetune", "env_step": 2500, "success": 0.75, "return": 1.0,
                  "q_data": -3.0, "q_uniform": float("nan")})
    log.close()
    got = _scalars(run.tb)
    assert ("pretrain/critic_loss", 500, 2.5) in got
    assert ("eval/success", 2500, 0.75) in got and ("eval/q_data", 2500, -3.0) in got
    assert not any(t in ("pretrain/note", "eval/q_uniform") for t, _, _ in got)


def test_wandb_run_gets_prefixed_metrics(tmp_path):
    class Recorder:
        def __init__(self):
            self.calls = []

        def log(self, d):
            self.calls.append(d)

    rec = Recorder()
    run = RunDir(tmp_path / "run")
    run.create()
    log = MetricsLogger(run, tensorboard=False, wandb_run=rec)
    log.log("finetune", 100, {"actor_loss": 0.5})
    log.log_eval({"env_step": 0, "success": 1.0, "return": 2.0, "q_data": -1.0, "q_uniform": -2.0})
    log.close()
    # rows of the online axis carry env_step, W&B's x-axis for them (pipeline/tracking.py)
    assert rec.calls[0] == {"finetune/actor_loss": 0.5, "finetune/step": 100, "env_step": 100}
    assert rec.calls[1] == {"eval/success": 1.0, "eval/return": 2.0, "eval/q_data": -1.0,
                            "eval/q_uniform": -2.0, "eval/env_step": 0, "env_step": 0}

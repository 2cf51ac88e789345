"""Verified checkpoints: checksummed files, the last two kept, a damaged one named and skipped,
`botorl resume --from NAME`, and corrupt checkpoint files ending in exit 2, not a traceback.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from botorl.cli import main as botorl_main
from botorl.errors import ConfigError, DataFormatError
from botorl.pipeline.checkpoint import CheckpointCorrupt, CheckpointManager


def _state(stage, step, done=False):
    return {"stage": stage, "step": step, "stage_done": done, "done_stages": [], "stage_seconds": {}}


def _save(m: CheckpointManager, stage, step, done=False, seed=0):
    name = f"{stage}-final" if step is None else f"{stage}-step{step:09d}"
    arrays = {"buffer": {"x": np.random.default_rng(seed).normal(size=100)}}
    m.save(name, state=_state(stage, step, done), arrays=arrays)
    return name


def _flip(path: Path, at: int = -20) -> None:
    b = bytearray(path.read_bytes())
    b[at] ^= 0xFF
    path.write_bytes(bytes(b))


def test_last_two_kept_and_finals(tmp_path):
    m = CheckpointManager(tmp_path)
    _save(m, "pretrain", None, True)
    names = [_save(m, "finetune", s, seed=s) for s in (10, 20, 30)]
    assert m.names() == ["finetune-step000000020", "finetune-step000000030", "pretrain-final"]
    assert m.latest()["name"] == names[-1]
    for n in m.names():
        assert m.verify(n) is None
    manifest = json.loads((tmp_path / names[-1] / "MANIFEST.json").read_text())
    assert set(manifest["files"]) == {"state.json", "buffer.npz"}


def test_damaged_newest_falls_back_to_previous(tmp_path, capsys):
    m = CheckpointManager(tmp_path)
    a = _save(m, "finetune", 10)
    b = _save(m, "finetune", 20)
    _flip(tmp_path / b / "buffer.npz")
    assert "sha256" in m.verify(b)
    assert m.latest()["name"] == a
    err = capsys.readouterr().err
    assert b in err and "Falling back to the previous checkpoint" in err and a in err
    assert json.loads((tmp_path / "latest.json").read_text())["name"] == a  # the pointer is repaired
    with pytest.raises(CheckpointCorrupt, match="sha256"):
        m.arrays(b, "buffer")
    with pytest.raises(ConfigError, match=a):
        m.verify_named(b)  # names the one that passes


def test_truncated_or_garbage_files(tmp_path, capsys):
    m = CheckpointManager(tmp_path)
    a = _save(m, "finetune", 10)
    b = _save(m, "finetune", 20)
    (tmp_path / b / "state.json").write_text("{not json")
    assert m.latest()["name"] == a
    (tmp_path / "latest.json").write_text("garbage")
    assert m.latest()["name"] == a
    (tmp_path / a / "buffer.npz").write_bytes(b"")
    assert m.latest() is None  # nothing passes: the resume starts over rather than trusting a damaged file
    assert "no checkpoint passes" in capsys.readouterr().err


def test_select_by_name(tmp_path):
    m = CheckpointManager(tmp_path)
    a = _save(m, "finetune", 10)
    _save(m, "finetune", 20)
    assert m.select(a)["name"] == a and m.latest()["name"] == a
    with pytest.raises(ConfigError, match="there are"):
        m.select("finetune-step999")


def test_legacy_checkpoint_without_manifest_is_read(tmp_path):
    m = CheckpointManager(tmp_path)
    a = _save(m, "finetune", 10)
    (tmp_path / a / "MANIFEST.json").unlink()
    assert m.verify(a) is None and m.latest()["name"] == a


def test_agent_file_checksum(tmp_path):
    import jax

    from botorl.agents import agent_file
    from botorl.agents.sac import SACAgent, SACConfig

    agent = SACAgent.create(SACConfig(actor_hidden_dims=(8,), critic_hidden_dims=(8,), num_critics=2), 3, 2, seed=0)
    p = agent_file.save(tmp_path / "a.ckpt", agent)
    back = agent_file.load(p, like=agent)
    assert all(np.array_equal(x, y) for x, y in zip(jax.tree_util.tree_leaves(agent), jax.tree_util.tree_leaves(back)))
    raw = bytearray(p.read_bytes())
    raw[len(raw) // 2] ^= 0x01  # one bit inside the parameters
    p.write_bytes(bytes(raw))
    with pytest.raises(DataFormatError, match="sha256|cannot be read"):
        agent_file.load(p, like=agent)


# ----------------------------------------------------------------------------- through the CLI
@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("ckpt") / "run"
    rc = botorl_main(["run", "--task", "pointmaze-umaze", "--profile", "smoke", "--no-progress", "--no-tensorboard",
                      "--online.steps", "80", "--checkpoint_every", "10", "--out", str(out)])
    assert rc == 0
    return out


def _copy(run: Path, tmp_path: Path) -> Path:
    d = tmp_path / "copy"
    shutil.copytree(run, d)
    (d / ".lock").unlink(missing_ok=True)
    return d


def _mark_running(d: Path) -> None:
    s = json.loads((d / "summary.json").read_text())
    s["status"] = "running"
    (d / "summary.json").write_text(json.dumps(s))


def _mid(run: Path) -> str:
    mids = [n for n in CheckpointManager(run / "checkpoints").names() if n.startswith("finetune-step")]
    assert len(mids) == 1, mids
    return mids[0]


def test_run_keeps_previous_checkpoint(finished_run):
    """Of several mid-fine-tuning checkpoints only the one before finetune-final is left (plus the finals)."""
    names = CheckpointManager(finished_run / "checkpoints").names()
    assert {"pretrain-final", "finetune-final"} <= set(names)
    assert _mid(finished_run) == "finetune-step000000070"


def test_resume_from_named_checkpoint(finished_run, tmp_path, capsys):
    d = _copy(finished_run, tmp_path)
    assert botorl_main(["resume", str(d), "--no-progress", "--from", _mid(d)]) == 0
    err = capsys.readouterr().err
    assert "finetune step 70" in err
    s = json.loads((d / "summary.json").read_text())
    assert s["status"] == "finished"
    steps = [json.loads(x)["step"] for x in (d / "metrics" / "finetune.jsonl").read_text().splitlines()]
    assert steps == sorted(set(steps))


def test_resume_from_damaged_checkpoint_exits_2(finished_run, tmp_path, capsys):
    d = _copy(finished_run, tmp_path)
    name = _mid(d)
    _flip(d / "checkpoints" / name / "buffer.npz")
    assert botorl_main(["resume", str(d), "--from", name]) == 2
    err = capsys.readouterr().err
    assert name in err and "sha256" in err and "Traceback" not in err
    assert botorl_main(["resume", str(d), "--from", "nope"]) == 2
    assert "there are" in capsys.readouterr().err


def test_resume_with_corrupt_latest_json(finished_run, tmp_path, capsys):
    d = _copy(finished_run, tmp_path)
    _mark_running(d)
    (d / "checkpoints" / "latest.json").write_text('{"name": ')
    assert botorl_main(["resume", str(d), "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "latest.json cannot be read" in err and "finetune-final" in err
    assert json.loads((d / "summary.json").read_text())["status"] == "finished"


def test_resume_buffer_truncated_without_manifest_exits_2(finished_run, tmp_path, capsys):
    """A damaged buffer.npz in a checkpoint that cannot be verified (no manifest) still ends in exit 2."""
    d = _copy(finished_run, tmp_path)
    name = _mid(d)
    ck = d / "checkpoints" / name
    (ck / "MANIFEST.json").unlink()
    (ck / "buffer.npz").write_bytes((ck / "buffer.npz").read_bytes()[:100])
    assert botorl_main(["resume", str(d), "--no-progress", "--from", name]) == 2
    err = capsys.readouterr().err
    assert "buffer.npz" in err and "Traceback" not in err
    s = json.loads((d / "summary.json").read_text())
    assert s["status"] == "failed" and "buffer.npz" in s["error"]


def test_latest_json_cannot_point_outside(tmp_path, capsys):
    m = CheckpointManager(tmp_path / "ck")
    a = _save(m, "finetune", 10)
    other = CheckpointManager(tmp_path / "other")
    _save(other, "finetune", 99)
    (tmp_path / "ck" / "latest.json").write_text(json.dumps({"name": "../other/finetune-step000000099"}))
    assert m.latest()["name"] == a
    assert "does not exist" in capsys.readouterr().err
    man = tmp_path / "ck" / a / "MANIFEST.json"
    d = json.loads(man.read_text())
    d["files"]["../../other/latest.json"] = {"size": 1, "sha256": "0"}
    man.write_text(json.dumps(d))
    assert "not a file of the folder" in m.verify(a)

"""botorl report reads run directories as data that can be hostile: whatever summary.json,
config.json and eval.csv hold (random bytes, truncations, symlinks, FIFOs, huge files), a run
is either read or skipped with a reason naming it -- never a traceback, a hang, or a read
through a link."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from botorl.experiments import pairs as PR
from botorl.experiments import runs as RN
from botorl.experiments.dip import dips_of

GOOD = {
    "summary.json": json.dumps({"task": "t", "method": "wsrl", "seed": 0, "status": "finished",
                                "success_initial": 1.0, "success_10k": 0.5, "success_final": 1.0}).encode(),
    "config.json": json.dumps({"task": "t", "method": "wsrl", "seed": 0, "pretrain": "calql", "offline": {},
                               "network": {}, "data": {}, "checkpoint_every": 5}).encode(),
    "eval.csv": b"stage,env_step,success\nfinetune,0,1\nfinetune,5000,0.5\nfinetune,10000,0.5\n",
}


def _write(root: Path, files: dict[str, bytes]) -> Path:
    d = root / "run"
    d.mkdir(parents=True)
    for name, data in files.items():
        (d / name).write_bytes(data)
    return d


def _read_all(root: Path):
    runs, skipped = RN.find_runs([root])
    dips_of(runs, 10_000)
    PR.find_pairs(runs)
    return runs, skipped


def test_a_good_run_is_read(tmp_path):
    runs, skipped = _read_all(_write(tmp_path, GOOD).parent)
    assert len(runs) == 1 and not skipped


hostile = st.one_of(
    st.binary(max_size=300),
    st.sampled_from([b"", b"{", b"[]", b"null", b'{"status": "finished", "task": {}, "method": []}',
                     b'{"status": "finished", "task": "t", "method": "wsrl", "seed": "x"}',
                     b'{"status": "finished", "task": "t", "method": "wsrl", "seed": 1e308}',
                     b"[" * 100_000, b"\xff\xfe\x00", b"env_step,success\n1e999,nan\n-1,2\n"]),
    st.builds(lambda good, n: good[:n], st.sampled_from(list(GOOD.values())), st.integers(0, 200)),
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(name=st.sampled_from(sorted(GOOD)), data=hostile)
def test_any_bytes_in_a_run_file_give_a_run_or_a_reason(tmp_path_factory, name, data):
    root = tmp_path_factory.mktemp("hostile")
    _write(root, {**GOOD, name: data})
    runs, skipped = _read_all(root)
    assert len(runs) + len(skipped) == 1
    if skipped:
        assert skipped[0].reason and skipped[0].path.name == "run"


@pytest.mark.parametrize("name", sorted(GOOD))
def test_links_fifos_and_huge_files_are_not_read(tmp_path, name):
    secret = tmp_path / "secret"
    secret.write_bytes(GOOD[name])
    # a symlink to a file that would read fine: refused, not followed
    d = _write(tmp_path / "link", {k: v for k, v in GOOD.items() if k != name})
    (d / name).symlink_to(secret)
    runs, skipped = _read_all(d.parent)
    if name == "config.json":  # the config is optional: the run is read without it
        assert len(runs) == 1 and runs[0].config == {}
    else:
        assert not runs and "not a regular file" in skipped[0].reason
    # a FIFO: no hang
    d = _write(tmp_path / "fifo", {k: v for k, v in GOOD.items() if k != name})
    os.mkfifo(d / name)
    runs, skipped = _read_all(d.parent)
    assert len(runs) + len(skipped) == 1 and (runs[0].config == {} if runs else "not a regular file" in skipped[0].reason)
    # a file past the size limit: refused by its size, without reading it
    d = _write(tmp_path / "huge", GOOD)
    with open(d / name, "r+b") as f:
        f.truncate(RN.CSV_LIMIT + 1)
    runs, skipped = _read_all(d.parent)
    assert len(runs) + len(skipped) == 1 and (runs[0].config == {} if runs else "bytes, more than" in skipped[0].reason)


def test_a_sweep_trial_log_that_is_a_link_or_huge_is_not_followed(tmp_path):
    d = tmp_path / "trial"
    d.mkdir()
    (tmp_path / "secret").write_text("the secret line\n")
    (d / "sweep-trial.log").symlink_to(tmp_path / "secret")
    runs, skipped = RN.find_runs([tmp_path])
    assert not runs and "the secret line" not in skipped[0].reason


@pytest.mark.parametrize("flags, needle", [(["--bootstrap", "1000000000"], "--bootstrap"),
                                           (["--bootstrap", "0"], "--bootstrap"),
                                           (["--confidence", "1.5"], "--confidence"),
                                           (["--confidence", "nan"], "--confidence")])
def test_report_refuses_bootstrap_settings_that_cannot_run(tmp_path, capsys, flags, needle):
    from botorl.cli import main as botorl_main

    root = _write(tmp_path, GOOD).parent
    assert botorl_main(["report", str(root), "--out", str(tmp_path / "rep"), *flags]) == 2
    assert needle in capsys.readouterr().err and not (tmp_path / "rep").exists()

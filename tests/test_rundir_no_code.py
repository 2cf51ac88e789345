"""A downloaded run directory runs no code (issue 39): the entry point and folder a config.json
records for a task of one's own are never imported, called or put on sys.path by ``eval``,
``resume``, ``export``, ``botorl.resume()``, a population or ``run --config``; only the user's
own ``--env`` (checked equal to the recorded one) or ``botorl.register_task`` makes the env. A
marker file proves that no planted module ran.

The run directories here are made by hand (a config.json and a checkpoint whose identity is
recomputed, as an attacker can): no training, so the file runs in seconds."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import subprocess_env as _env

from botorl.cli import main as botorl_main

PLANT = """
import pathlib
pathlib.Path({marker!r}).write_text("ran")
def make_env(seed):
    pathlib.Path({marker!r}).write_text("called")
    raise SystemExit(0)
"""


def _custom_config(entry: str, path: str | None, **env):
    """A smoke config whose task is 'a task of one's own' named by ``entry`` (no env is made)."""
    from dataclasses import replace

    from botorl.configs.build import build_config
    from botorl.configs.schema import EnvConfig

    cfg = build_config(["--task", "pointmaze-umaze", "--profile", "smoke"])
    e = EnvConfig(entry=entry, path=path, max_steps=50, success_key="success", obs_dim=4, action_dim=2,
                  action_low=(-1.0, -1.0), action_high=(1.0, 1.0), **env)
    return replace(cfg, task="evil.task", env=e, data=replace(cfg.data, path="/nonexistent/logged.npz"))


def _plant_run(d: Path, entry: str, marker: Path, *, relative: bool = False, **env) -> Path:
    """A run directory holding evilmod.py, a config.json naming ``entry`` with env.path pointing at
    the directory, and a checkpoint whose identity is recomputed to match (what an attacker can)."""
    from botorl.configs.schema import run_identity, to_dict

    d.mkdir(parents=True)
    (d / "evilmod.py").write_text(PLANT.format(marker=str(marker)))
    cfg = _custom_config(entry, "." if relative else str(d.resolve()), **env)
    (d / "config.json").write_text(json.dumps(to_dict(cfg)))
    ck = d / "checkpoints" / "pretrain-final"
    ck.mkdir(parents=True)
    state = {"stage": "pretrain", "stage_done": True, "step": None, "done_stages": ["pretrain"],
             "stage_seconds": {}, "identity": [run_identity(cfg)]}
    (ck / "state.json").write_text(json.dumps(state))
    (d / "checkpoints" / "latest.json").write_text(json.dumps({"name": "pretrain-final", "stage": "pretrain",
                                                               "step": None, "stage_done": True}))
    return d


ENTRIES = ["code:interact", "os:_exit", "this:x", "evilmod:make_env"]


@pytest.fixture(scope="module")
def planted(tmp_path_factory):
    root = tmp_path_factory.mktemp("planted")
    marker = root / "MARKER"
    runs = {e: _plant_run(root / e.replace(":", "_"), e, marker) for e in ENTRIES}
    runs["relative"] = _plant_run(root / "relative", "evilmod:make_env", marker, relative=True)
    return root, marker, runs


@pytest.mark.parametrize("entry", ENTRIES + ["relative"])
@pytest.mark.parametrize("command", ["eval", "resume", "export"])
def test_a_planted_entry_point_is_never_imported(planted, capsys, entry, command, monkeypatch):
    root, marker, runs = planted
    d = runs[entry]
    monkeypatch.chdir(d)  # the directory itself as the current folder: still nothing imported from it
    before = set(sys.modules)
    code = botorl_main([command, str(d)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert not marker.exists(), f"{command} ran the planted {entry}"
    assert "--env" in err and "Traceback" not in err, err
    assert not {"evilmod", "this", "code"} & (set(sys.modules) - before)
    assert str(d.resolve()) not in sys.path


def test_botorl_resume_from_python_imports_nothing(planted):
    import botorl
    from botorl.errors import BotorlError

    root, marker, runs = planted
    for entry in ("evilmod:make_env", "this:x"):
        with pytest.raises(BotorlError, match="--env"):
            botorl.resume(runs[entry], progress=False)
    assert not marker.exists() and "evilmod" not in sys.modules


def test_code_interact_reads_no_stdin_and_os_exit_is_exit_2(planted):
    """In a subprocess: ``code:interact`` would open a prompt on stdin, ``os:_exit`` exit 0."""
    root, marker, runs = planted
    for entry in ("code:interact", "os:_exit"):
        p = subprocess.run([sys.executable, "-m", "botorl.cli", "eval", str(runs[entry])], input="print('pwned')\n",
                           capture_output=True, text=True, env=_env(), timeout=120, cwd=runs[entry])
        assert p.returncode == 2 and "--env" in p.stderr and "pwned" not in p.stdout + p.stderr, p.stderr[-2000:]
    assert not marker.exists()


def test_run_config_and_population_import_nothing(planted, tmp_path, capsys):
    from botorl.configs.schema import to_dict

    root, marker, runs = planted
    cfg = json.loads((runs["evilmod:make_env"] / "config.json").read_text())
    f = tmp_path / "trial.json"
    f.write_text(json.dumps(cfg))
    assert botorl_main(["run", "--config", str(f), "--out", str(tmp_path / "out")]) == 2
    assert "--env" in capsys.readouterr().err

    # a population whose shared config names the planted module
    pop = tmp_path / "pop"
    pop.mkdir()
    (pop / "evilmod.py").write_text(PLANT.format(marker=str(marker)))
    c = _custom_config("evilmod:make_env", str(pop.resolve()))
    from dataclasses import replace

    member = pop / "seed0"
    member.mkdir()
    (member / "config.json").write_text(json.dumps(to_dict(replace(c, out=str(member)))))
    (pop / "population.json").write_text(json.dumps({"config": to_dict(c), "members": [{"name": "seed0"}],
                                                     "status": "running"}))
    assert botorl_main(["resume", str(pop)]) == 2
    err = capsys.readouterr().err
    assert "--env" in err and "Traceback" not in err, err
    assert not marker.exists() and not (tmp_path / "out").exists()


def test_env_given_must_be_the_recorded_one(planted, capsys, monkeypatch, tmp_path):
    root, marker, runs = planted
    d = runs["evilmod:make_env"]
    monkeypatch.chdir(tmp_path)
    # another entry than the recorded one: refused before it is imported
    assert botorl_main(["eval", str(d), "--env", "os:_exit"]) == 2
    assert "trained on the entry point 'evilmod:make_env'" in capsys.readouterr().err
    # the recorded one, given by the user, is the user's choice: imported from the current folder
    # and PYTHONPATH only (the run directory's own folder is not searched)
    assert botorl_main(["eval", str(d), "--env", "evilmod:make_env"]) == 2
    assert "cannot import module 'evilmod'" in capsys.readouterr().err
    assert not marker.exists()
    # a task of botorl's own takes no --env
    from botorl.configs.schema import to_dict

    own = tmp_path / "own"
    own.mkdir()
    from botorl.configs.build import build_config

    (own / "config.json").write_text(json.dumps(to_dict(build_config(["--task", "pointmaze-umaze", "--profile", "smoke"]))))
    assert botorl_main(["resume", str(own), "--env", "mytask:make_env"]) == 2
    assert "drop --env" in capsys.readouterr().err


def test_sys_exit_in_make_env_is_exit_2(tmp_path, monkeypatch, capsys):
    """``--env sys:exit`` used to exit 0 having done nothing (the probe caught Exception only)."""
    monkeypatch.chdir(tmp_path)
    import numpy as np

    np.savez(tmp_path / "d.npz", observations=np.zeros((4, 2), np.float32), actions=np.zeros((4, 1), np.float32),
             rewards=np.zeros(4, np.float32), next_observations=np.zeros((4, 2), np.float32),
             terminals=np.zeros(4, np.float32))
    code = botorl_main(["run", "--env", "sys:exit", "--data.path", "d.npz", "--env-max-steps", "5", "--profile",
                        "smoke", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and "SystemExit" in err and "Traceback" not in err, err


def test_counts_a_config_json_gives_are_checked_before_the_env_is_made(planted, tmp_path, capsys, monkeypatch):
    """env.max_steps = 10**12 with a success key no env sets spun forever in the env probe, before the
    identity check; a checkpoint's sizes and the eval's episodes are bounded before any work."""
    root, marker, runs = planted
    d = tmp_path / "huge"
    _plant_run(d, "evilmod:make_env", marker)
    cfg = json.loads((d / "config.json").read_text())
    for field, value, words in (("max_steps", 10**12, "--env.max_steps = 1000000000000 is invalid"),
                                ("obs_dim", 10**9, "--env.obs_dim = 1000000000 is invalid")):
        (d / "config.json").write_text(json.dumps({**cfg, "env": {**cfg["env"], field: value}}))
        for cmd in (["eval", str(d), "--env", "evilmod:make_env"], ["resume", str(d)], ["export", str(d)]):
            assert botorl_main(cmd) == 2, cmd
            err = capsys.readouterr().err
            assert words in err and "Traceback" not in err, (cmd, err)
    assert botorl_main(["eval", str(runs["this:x"]), "--episodes", str(10**12)]) == 2
    assert "--episodes 1000000000000 is out of range: give a number from 1 to 1,000" in capsys.readouterr().err
    assert not marker.exists()


def test_a_config_with_a_null_section_is_exit_2(planted, tmp_path, capsys):
    root, marker, runs = planted
    cfg = json.loads((runs["this:x"] / "config.json").read_text())
    f = tmp_path / "trial.json"
    f.write_text(json.dumps({**cfg, "data": None}))
    assert botorl_main(["run", "--config", str(f), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "'data' is null" in err and "Traceback" not in err, err
    d = tmp_path / "run"
    d.mkdir()
    (d / "config.json").write_text(json.dumps({**cfg, "network": None}))
    assert botorl_main(["eval", str(d)]) == 2
    err = capsys.readouterr().err
    assert "'network' is null" in err and "Traceback" not in err, err


@pytest.mark.slow
@pytest.mark.timeout(900)  # 18 botorl processes, each allowed 30 s
def test_every_case_is_exit_2_within_30_s_under_a_4_gb_address_space(planted, tmp_path):
    """The issue's bar, measured as a user meets it: each hostile case as its own `botorl`
    process under `ulimit -v 4000000`, exit 2 within 30 s, no traceback, nothing written outside
    the directories the case names (the current folder, a canary folder beside them)."""
    import os
    import time

    import h5py
    import numpy as np

    root, marker, runs = planted
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    canary = tmp_path / "canary"
    canary.mkdir()
    (canary / "keep").write_text("keep me")
    huge = tmp_path / "huge"
    _plant_run(huge, "evilmod:make_env", marker)
    cfg = json.loads((huge / "config.json").read_text())
    (huge / "config.json").write_text(json.dumps({**cfg, "env": {**cfg["env"], "max_steps": 10**12}}))
    null = tmp_path / "null.json"
    null.write_text(json.dumps({**cfg, "data": None}))
    # a built-in task's config whose SAC critic is 10**9 units wide, past the bounds on its source
    # (network.critic_hidden_dims): it was an out-of-memory traceback (exit 1)
    from botorl.configs.presets import make_preset
    from botorl.configs.resolve import resolve
    from botorl.configs.schema import to_dict

    wide_cfg = to_dict(resolve(make_preset("pointmaze-umaze", "smoke", "boto")))
    wide_cfg["online"]["sac"]["critic_hidden_dims"] = [10**9]
    wide = tmp_path / "wide.json"
    wide.write_text(json.dumps(wide_cfg))
    fifo = tmp_path / "fifo.hdf5"
    os.mkfifo(fifo)
    ext = tmp_path / "ext.hdf5"
    with h5py.File(ext, "w") as f:
        for k, shape in (("observations", (5, 3)), ("actions", (5, 2)), ("terminals", (5,))):
            f.create_dataset(k, data=np.zeros(shape, np.float32))
        f.create_dataset("rewards", shape=(5,), dtype=np.float32, external=[(str(fifo), 0, 20)])
    bomb = tmp_path / "bomb.npz"
    import zipfile

    header = io_header((2**40, 3))
    with zipfile.ZipFile(bomb, "w") as z:
        z.writestr("observations.npy", header)
    d = str(runs["evilmod:make_env"])
    cases = [
        ["eval", d], ["resume", d], ["export", d, "--out", str(tmp_path / "p.onnx")],
        ["eval", str(runs["code:interact"])], ["eval", str(runs["os:_exit"])], ["resume", str(runs["relative"])],
        ["eval", str(huge), "--env", "evilmod:make_env"],
        ["run", "--env", "sys:exit", "--data.path", str(bomb), "--env-max-steps", "5", "--out", str(tmp_path / "o1")],
        ["run", "--config", str(null), "--out", str(tmp_path / "o2")],
        ["run", "--config", str(wide), "--out", str(tmp_path / "o5")],
        ["data", "info", str(fifo)], ["data", "info", str(ext)], ["data", "info", str(bomb)],
        ["export", d, "--out", "/dev/null", "--force"], ["export", d, "--out", "/proc/self/x.onnx"],
        ["run", "--profile", "smoke", "--network.num-critics", "1000000", "--out", str(tmp_path / "o3")],
        ["run", "--profile", "smoke", "--data.steps", "1000000000000000", "--out", str(tmp_path / "o4")],
        ["eval", d, "--episodes", str(10**12)],
    ]
    slowest = 0.0
    for argv in cases:
        t0 = time.monotonic()
        p = subprocess.run(["bash", "-c", 'ulimit -v 4000000 && exec "$@"', "bash", sys.executable, "-m", "botorl.cli",
                            *argv], cwd=cwd, env=_env(), capture_output=True, text=True, timeout=60,
                           input="print('pwned')\n")
        took = time.monotonic() - t0
        slowest = max(slowest, took)
        assert p.returncode == 2 and took < 30, (argv, p.returncode, took, p.stderr[-2000:])
        assert "Traceback" not in p.stderr and "pwned" not in p.stdout + p.stderr, (argv, p.stderr[-2000:])
    assert not marker.exists() and list(cwd.iterdir()) == [] and (canary / "keep").read_text() == "keep me"
    assert Path("/dev/null").is_char_device() and fifo.is_fifo()
    print(f"{len(cases)} cases, slowest {slowest:.1f} s")


def io_header(shape) -> bytes:
    import io

    import numpy as np

    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "<f4", "fortran_order": False, "shape": shape})
    return buf.getvalue()


def test_the_env_probe_is_bounded_in_steps():
    """The probe looks for the success key in one episode of random actions: at most PROBE_STEPS
    steps (and PROBE_SECONDS) whatever the horizon, so an env that never says success cannot hold
    botorl up."""
    import gymnasium as gym
    import numpy as np
    from gymnasium import spaces

    from botorl.envs import user

    class Silent(gym.Env):
        observation_space = spaces.Box(-1, 1, (2,), np.float32)
        action_space = spaces.Box(-1, 1, (1,), np.float32)
        steps = 0

        def reset(self, *, seed=None, options=None):
            return np.zeros(2, np.float32), {}

        def step(self, a):
            Silent.steps += 1
            return np.zeros(2, np.float32), 0.0, False, False, {}

    task = user.probe(lambda seed: Silent(), 10**7, "success", name="silent")
    assert Silent.steps == user.PROBE_STEPS and task.success_key is None

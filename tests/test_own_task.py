"""A task of one's own (issue 26, docs/own-task.md): the Python API, ``botorl run --env``, resume
after kill -9, the policy outside botorl, and every bad input's exit code and message."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import sigkill_in_finetune
from helpers import load_example
from helpers import subprocess_env as _env
from gymnasium import spaces

import botorl
from botorl.cli import main as cli_main
from botorl.envs.user import action_from_env, action_to_env, flatten_obs, obs_keys_of


REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "own_task.py"


def _example():
    return load_example("own_task")


BADENVS = textwrap.dedent('''
    import gymnasium as gym
    import numpy as np
    from gymnasium import spaces

    class Discrete(gym.Env):
        observation_space = spaces.Box(-1, 1, (4,), np.float32)
        action_space = spaces.Discrete(4)
        def reset(self, *, seed=None, options=None):
            return np.zeros(4, np.float32), {}
        def step(self, a):
            return np.zeros(4, np.float32), 0.0, False, False, {}

    class NoSuccess(gym.Env):
        observation_space = spaces.Box(-1, 1, (4,), np.float32)
        action_space = spaces.Box(-0.1, 0.1, (2,), np.float32)
        def reset(self, *, seed=None, options=None):
            super().reset(seed=seed)
            self.t = 0
            return np.zeros(4, np.float32), {}
        def step(self, a):
            self.t += 1
            return np.zeros(4, np.float32), 0.0, False, self.t >= 50, {"reached": False}

    def make_discrete(seed):
        return Discrete()

    def make_no_success(seed):
        return NoSuccess()
''')


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A folder as a user has it: mytask.py (the example), badenvs.py, logged.npz and bad variants."""
    d = tmp_path_factory.mktemp("own")
    shutil.copy(EXAMPLE, d / "mytask.py")
    (d / "badenvs.py").write_text(BADENVS)
    (d / "broken.py").write_text("raise RuntimeError('this module is broken')\n")
    ex = _example()
    data = ex.logged_data(episodes=40)
    ex.save(data, d / "logged.npz")
    flat = {k: (np.concatenate([v["goal"], v["position"]], axis=1) if isinstance(v, dict) else v) for k, v in data.items()}
    np.savez(d / "obs5.npz", **{**flat, "observations": np.pad(flat["observations"], ((0, 0), (0, 1))),
                                "next_observations": np.pad(flat["next_observations"], ((0, 0), (0, 1)))})
    np.savez(d / "act3.npz", **{**flat, "actions": np.pad(flat["actions"], ((0, 0), (0, 1)))})
    rewards = flat["rewards"].copy()
    rewards[7] = np.nan
    np.savez(d / "nan.npz", **{**flat, "rewards": rewards})
    return {"dir": d, "data": data, "flat": flat}


def test_import_botorl_stays_light():
    code = ("import sys, botorl; heavy = [m for m in ('jax', 'flax', 'gymnasium', 'tyro') if m in sys.modules]; "
            "assert not heavy, heavy; assert callable(botorl.run) and 'jax' not in sys.modules; "
            "assert {'register_task', 'run', 'resume', 'load_policy', 'load_agent'} <= set(dir(botorl))")
    proc = subprocess.run([sys.executable, "-c", code], env=_env(), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr


def test_override_args():
    from botorl.api import override_args

    assert override_args({"online__steps": 5, "network": {"layer_norm": False, "critic_hidden_dims": (8, 8)},
                          "progress": True, "online.buffer_capacity": None}) == [
        "--online.steps", "5", "--network.no-layer-norm", "--network.critic_hidden_dims", "8", "8", "--progress",
        "--online.buffer_capacity", "None"]


# ------------------------------------------------------------------ the pure transformations
def test_flatten_order_and_action_maps():
    space = spaces.Dict({"b": spaces.Box(-1, 1, (2,)), "a": spaces.Dict({"y": spaces.Box(-1, 1, (1,)),
                                                                            "x": spaces.Box(-1, 1, (2, 2))})})
    keys = obs_keys_of(space)
    assert keys == ("a/x", "a/y", "b")
    obs = {"b": np.array([7.0, 8.0]), "a": {"y": np.array([5.0]), "x": np.array([[1.0, 2.0], [3.0, 4.0]])}}
    assert flatten_obs(obs, keys).tolist() == [1, 2, 3, 4, 5, 7, 8]
    batch = {"b": np.stack([obs["b"]] * 3), "a": {"y": np.stack([obs["a"]["y"]] * 3), "x": np.stack([obs["a"]["x"]] * 3)}}
    assert flatten_obs(batch, keys, batched=True).shape == (3, 7)
    low, high = np.array([-0.1, 0.0]), np.array([0.1, 4.0])
    assert action_to_env([-1, 1], low, high).tolist() == [-0.1, 4.0]
    assert action_to_env([0, 0], low, high).tolist() == pytest.approx([0.0, 2.0])
    a = np.array([[0.05, 1.0], [-0.1, 3.9]])
    assert np.allclose(action_to_env(action_from_env(a, low, high), low, high), a)


def test_task_env_rescales_actions_and_flattens(work):
    sys.path.insert(0, str(work["dir"]))
    spec = botorl.register_task("unit-point", "mytask:make_env", work["data"], max_episode_steps=50)
    env = spec.make_env(0)
    obs, info = env.reset()
    assert obs.shape == (4,) and obs.dtype == np.float32 and info["success"] == 0.0
    inner = env.unwrapped
    before = inner.pos.copy()
    env.step(np.array([1.0, -1.0]))  # botorl's [-1, 1] -> the env's [-0.1, 0.1]
    assert np.allclose(inner.pos - before, [0.1, -0.1])
    assert obs.tolist() == pytest.approx([0.6, 0.6, *before.tolist()])  # sorted keys: goal, position


# ------------------------------------------------------------------ bad input: exit 2 / BotorlError
def _cli(work, monkeypatch, capsys, *args):
    # as the `botorl` console script starts: the current folder is not on sys.path, so the entry
    # point's module is found only because botorl looks there first (as `python -m` does)
    monkeypatch.chdir(work["dir"])
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", ".", str(work["dir"]))])
    for name in ("mytask", "badenvs", "broken"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    out = work["dir"] / "runs" / f"bad-{time.time_ns()}"
    code = cli_main(["run", *args, "--profile", "smoke", "--no-progress", "--out", str(out)])
    err = capsys.readouterr().err
    assert not out.exists(), "a bad input must fail before the run directory exists"
    return code, " ".join(err.split())


CLI_CASES = [
    (["--env", "mytask:make_env", "--data.path", "obs5.npz", "--env-max-steps", "50"],
     "observations have 5 dimensions, but the env's have 4"),
    (["--env", "mytask:make_env", "--data.path", "act3.npz", "--env-max-steps", "50"],
     "actions have 3 dimensions, but the env's action space has 2"),
    (["--env", "badenvs:make_discrete", "--data.path", "logged.npz", "--env-max-steps", "50"],
     "need a gymnasium.spaces.Box action space"),
    (["--env", "mytask:make_env", "--data.path", "nan.npz", "--env-max-steps", "50"],
     "field 'rewards' has 1 NaN/inf values (first at row 7"),
    (["--env", "nosuchmodule:make_env", "--data.path", "logged.npz", "--env-max-steps", "50"],
     "cannot import module 'nosuchmodule'"),
    (["--env", "mytask:nosuch", "--data.path", "logged.npz", "--env-max-steps", "50"],
     "has no function 'nosuch'"),
    (["--env", "broken:make_env", "--data.path", "logged.npz", "--env-max-steps", "50"],
     "importing module 'broken' failed: RuntimeError: this module is broken"),
    (["--env", "mytask", "--data.path", "logged.npz", "--env-max-steps", "50"], "as MODULE:FUNCTION"),
    (["--env", "badenvs:make_no_success", "--data.path", "logged.npz", "--env-max-steps", "50", "--success-key",
      "done"], "--success-key 'done' is not in the env's info (keys seen: reached)"),
    (["--env", "mytask:make_env", "--data.path", "logged.npz"], "needs --env-max-steps N"),
    (["--env", "mytask:make_env", "--env-max-steps", "50"], "needs --data.path FILE"),
    (["--env", "mytask:make_env", "--data.path", "missing.npz", "--env-max-steps", "50"], "missing.npz: no such file"),
]


@pytest.mark.parametrize("args,message", CLI_CASES, ids=[c[1][:40] for c in CLI_CASES])
def test_cli_bad_input_exit_2(work, monkeypatch, capsys, args, message):
    code, err = _cli(work, monkeypatch, capsys, *args)
    assert code == 2
    assert message in err, err


def test_python_bad_input_raises(work, monkeypatch):
    monkeypatch.chdir(work["dir"])
    ex = _example()
    flat = work["flat"]

    def reg(make_env=ex.make_env, data=work["data"], **kw):
        return botorl.register_task("bad-task", make_env, data, kw.pop("max_episode_steps", 50), **kw)

    cases = [
        (dict(data={**flat, "observations": np.pad(flat["observations"], ((0, 0), (0, 1)))}),
         "observations have 5 dimensions, but the env's have 4"),
        (dict(data={**flat, "actions": flat["actions"][:, :1]}), "actions have 1 dimensions, but the env's action space has 2"),
        (dict(make_env="badenvs:make_discrete"), "need a gymnasium.spaces.Box action space"),
        (dict(data={**flat, "next_observations": np.where(np.arange(len(flat["rewards"]))[:, None] == 3, np.nan,
                                                          flat["next_observations"])}),
         "field 'next_observations' has 4 NaN/inf values (first at row 3"),
        (dict(make_env="nosuchmodule:make_env"), "cannot import module 'nosuchmodule'"),
        (dict(make_env="badenvs:make_no_success", success_key="done"), "'done' is not in the env's info"),
        (dict(data={k: v for k, v in flat.items() if k != "terminals"}), "missing 'terminals'"),
        (dict(max_episode_steps=0), "max_episode_steps"),
        (dict(domain="moon"), "domain 'moon' is not one of"),
        (dict(data=[1, 2, 3]), "dataset is a list"),
    ]
    for kw, message in cases:
        with pytest.raises(botorl.BotorlError) as info:
            reg(**kw)
        assert message in " ".join(str(info.value).split()), (kw, str(info.value))
    with pytest.raises(botorl.BotorlError, match="one of botorl's tasks"):
        botorl.register_task("pointmaze-umaze", ex.make_env, work["data"], 50)


def test_actions_outside_the_env_box(work, monkeypatch, capsys):
    flat = dict(work["flat"])
    flat["actions"] = flat["actions"] * 3.0  # up to 0.3 where the box ends at 0.1
    np.savez(work["dir"] / "wide.npz", **flat)
    code, err = _cli(work, monkeypatch, capsys, "--env", "mytask:make_env", "--data.path", "wide.npz",
                     "--env-max-steps", "50")
    assert code == 2 and "the logged actions leave the env's action box (low [-0.1" in err, err


# ------------------------------------------------------------------ success off, from Python
def test_missing_success_key_turns_success_off(work, monkeypatch, capsys, tmp_path):
    monkeypatch.chdir(work["dir"])
    sys.path.insert(0, str(work["dir"]))
    import badenvs

    rng = np.random.default_rng(0)
    n = 200
    data = {"observations": np.zeros((n, 4)), "next_observations": np.zeros((n, 4)),
            "actions": rng.uniform(-0.1, 0.1, (n, 2)), "rewards": np.zeros(n), "terminals": np.zeros(n),
            "timeouts": (np.arange(n) % 50) == 49}
    botorl.register_task("no-success", badenvs.make_no_success, data, max_episode_steps=50)
    assert "the env's info has no 'success' key (keys seen: reached), so success is off" in capsys.readouterr().err
    summary = botorl.run("no-success", method="wsrl", profile="smoke", out=tmp_path / "run", progress=False,
                         tensorboard=False)
    printed = capsys.readouterr().out
    assert summary["status"] == "finished"
    assert "no 'success' key" in summary["success_off"] and "success is off" in printed
    cfg = json.loads((tmp_path / "run" / "config.json").read_text())
    assert cfg["env"]["entry"] == "badenvs:make_no_success" and cfg["env"]["success_key"] is None
    assert cli_main(["report", str(tmp_path / "run"), "--out", str(tmp_path / "report")]) == 0
    assert "success is off on no-success" in (tmp_path / "report" / "report.md").read_text()

    # the policy's chain is the pure functions, so an exporter can rebuild it
    policy = botorl.load_policy(tmp_path / "run")
    obs = rng.normal(size=(5, 4)).astype(np.float32)
    agent = botorl.load_agent(tmp_path / "run")
    expected = action_to_env(np.asarray(agent.eval_actions(flatten_obs(obs, None, batched=True))),
                             [-0.1, -0.1], [0.1, 0.1])
    got = policy(obs)
    assert got.shape == (5, 2) and np.allclose(got, expected, atol=1e-6)
    assert np.all(np.abs(got) <= 0.1 + 1e-7)
    assert policy(obs[0]).shape == (2,)


# ------------------------------------------------------------------ the example, from Python
@pytest.mark.timeout(600)
def test_example_runs(tmp_path):
    proc = subprocess.run([sys.executable, str(EXAMPLE), "--profile", "smoke", "--out", str(tmp_path / "runs")],
                          cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "boto: status finished" in proc.stdout and "wsrl: status finished" in proc.stdout
    assert "boto's policy in a plain Gymnasium loop: success" in proc.stdout
    for method in ("boto", "wsrl"):
        s = json.loads((tmp_path / "runs" / method / "summary.json").read_text())
        assert s["status"] == "finished" and s["task"] == "point-goal" and s["method"] == method


# ------------------------------------------------------------------ the CLI: run, kill -9, resume
# slow (~60 s): kill -9 and resume are tested on the shipped tasks (test_reliability_resume), and a
# task of one's own runs end to end in test_example_runs
@pytest.mark.slow
@pytest.mark.timeout(600)
def test_cli_entry_point_kill_resume_eval_policy(work, tmp_path):
    cwd = tmp_path / "user"
    cwd.mkdir()
    for f in ("mytask.py", "logged.npz"):
        shutil.copy(work["dir"] / f, cwd / f)
    out = cwd / "runs" / "killed"
    cmd = [sys.executable, "-m", "botorl.cli", "run", "--env", "mytask:make_env", "--data.path", "logged.npz",
           "--env-max-steps", "50", "--profile", "smoke", "--no-progress", "--no-tensorboard", "--online.steps", "400",
           "--checkpoint_every", "50", "--eval.interval", "100", "--out", str(out)]
    killed_at, _ = sigkill_in_finetune(cmd, out, cwd=cwd, timeout=420)
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["task"] == "mytask.make_env" and cfg["env"]["entry"] == "mytask:make_env"
    assert cfg["env"]["path"] == str(cwd.resolve()) and cfg["data"]["path"] == str((cwd / "logged.npz").resolve())
    assert cfg["env"]["obs_keys"] == ["goal", "position"] and cfg["env"]["action_high"] == pytest.approx([0.1, 0.1])

    # resumed from another folder: the entry point is given again with --env (issue 39: botorl never
    # imports what config.json names, nor puts its recorded folder on sys.path), found on PYTHONPATH
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    bare = subprocess.run([sys.executable, "-m", "botorl.cli", "resume", str(out), "--no-progress"], cwd=elsewhere,
                          env=_env(), capture_output=True, text=True, timeout=120)
    assert bare.returncode == 2 and "--env mytask:make_env" in bare.stderr, bare.stderr[-2000:]
    user_env = {**_env(), "PYTHONPATH": f"{cwd}:{_env().get('PYTHONPATH', '')}"}
    res = subprocess.run([sys.executable, "-m", "botorl.cli", "resume", str(out), "--no-progress", "--env",
                          "mytask:make_env"], cwd=elsewhere, env=user_env, capture_output=True, text=True, timeout=420)
    assert res.returncode == 0, res.stderr[-3000:]
    assert json.loads((out / "summary.json").read_text())["status"] == "finished"
    ev = subprocess.run([sys.executable, "-m", "botorl.cli", "eval", str(out), "--episodes", "2", "--env",
                         "mytask:make_env"], cwd=elsewhere, env=user_env, capture_output=True, text=True, timeout=300)
    assert ev.returncode == 0 and "success" in ev.stdout, ev.stderr[-3000:]

    # the policy in a process that registers nothing and cannot import mytask
    script = textwrap.dedent(f"""
        import numpy as np, botorl
        p = botorl.load_policy({str(out)!r})
        a = p(np.random.default_rng(0).normal(size=(7, 4)).astype(np.float32))
        assert a.shape == (7, 2) and a.dtype == np.float32 and np.all(np.abs(a) <= 0.1 + 1e-7), a
        one = p({{"goal": np.array([0.6, 0.6]), "position": np.array([0.0, 0.0])}})
        assert one.shape == (2,)
        s = botorl.load_policy({str(out)!r}, deterministic=False)(np.zeros((3, 4), np.float32))
        assert s.shape == (3, 2) and np.all(np.abs(s) <= 0.1 + 1e-7)
        import sys; assert "mytask" not in sys.modules
        print("policy ok")
    """)
    pol = subprocess.run([sys.executable, "-c", script], cwd=elsewhere, env=_env(), capture_output=True, text=True,
                         timeout=300)
    assert pol.returncode == 0 and "policy ok" in pol.stdout, pol.stderr[-3000:]

    # the module moved away: resume says so with exit 2
    (cwd / "mytask.py").rename(cwd / "mytask_moved.py")
    sys.modules.pop("mytask", None)
    (out / "summary.json").write_text(json.dumps({**json.loads((out / "summary.json").read_text()), "status": "running"}))
    gone = subprocess.run([sys.executable, "-m", "botorl.cli", "resume", str(out), "--no-progress", "--env",
                           "mytask:make_env"], cwd=elsewhere, env=user_env, capture_output=True, text=True, timeout=120)
    assert gone.returncode == 2 and "cannot import module 'mytask'" in gone.stderr, gone.stderr[-2000:]

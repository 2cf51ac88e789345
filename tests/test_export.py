"""``botorl export`` and ``eval --policy`` (issue 33, docs/deploy.md).

Without the export extra (CI installs only ``.[test]``): every bad input's exit code and message,
the missing extra's install line, the graph's JAX function against ``load_policy``, and the
contract's layout. With it (``pytest.importorskip``): the written model through onnxruntime
alone against ``load_policy`` on 256 dataset observations, ``eval --policy`` against ``eval``,
the mismatch exit 1, and the docs page's loop run with neither botorl nor JAX importable.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from botorl.cli import main as cli_main
from botorl.pipeline import export as E

REPO = Path(__file__).resolve().parents[1]
INSTALL = 'pip install "botorl[export]"'


def _botorl(*argv, cwd=None) -> subprocess.CompletedProcess:
    import os

    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return subprocess.run([sys.executable, "-m", "botorl.cli", *map(str, argv)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def umaze(tmp_path_factory) -> Path:
    """A finished smoke run on pointmaze-umaze (every stage, a few steps)."""
    out = tmp_path_factory.mktemp("export") / "umaze"
    res = _botorl("run", "--task", "pointmaze-umaze", "--profile", "smoke", "--seed", "0", "--no-progress",
                  "--no-tensorboard", "--out", out)
    assert res.returncode == 0, res.stderr[-3000:]
    return out


def _dataset_obs(run: Path, n: int = 256) -> np.ndarray:
    run_, cfg = E.read_run(run)
    obs, source = E.verification_observations(cfg, run_, n, seed=1)
    assert source == "dataset" and obs.shape == (n, 4)
    return obs


def _no_extra(monkeypatch):
    for m in ("onnx", "onnxruntime", "jax2onnx"):
        monkeypatch.setitem(sys.modules, m, None)  # `import m` raises ImportError


# ------------------------------------------------------------------ without the extra
def test_missing_extra_exit_2_with_install_line(umaze, tmp_path, monkeypatch, capsys):
    _no_extra(monkeypatch)
    assert cli_main(["export", str(umaze), "--out", str(tmp_path / "p.onnx")]) == 2
    err = capsys.readouterr().err
    assert INSTALL in err and "jax2onnx" in err and "onnxruntime" in err
    assert not (tmp_path / "p.onnx").exists() and not (tmp_path / "p.onnx.json").exists()
    model = tmp_path / "m.onnx"
    model.write_bytes(b"not checked before the runtime is there")
    assert cli_main(["eval", str(umaze), "--policy", str(model)]) == 2
    assert INSTALL in capsys.readouterr().err


def test_bad_inputs_exit_2(umaze, tmp_path, capsys):
    # no finished stage: a run directory whose first stage has not written its checkpoint
    fresh = tmp_path / "fresh"
    (fresh / "checkpoints").mkdir(parents=True)
    shutil.copy(umaze / "config.json", fresh / "config.json")
    assert cli_main(["export", str(fresh)]) == 2
    assert "has no finished stage yet" in capsys.readouterr().err

    assert cli_main(["export", str(umaze), "--checkpoint", "nosuch", "--out", str(tmp_path / "x.onnx")]) == 2
    err = capsys.readouterr().err
    assert "checkpoint 'nosuch' is not in" in err and "pretrain-final" in err

    taken = tmp_path / "taken.onnx"
    taken.write_bytes(b"a file of the user's")
    assert cli_main(["export", str(umaze), "--out", str(taken)]) == 2
    assert "exists; pass --force" in capsys.readouterr().err and taken.read_bytes() == b"a file of the user's"
    contract_only = tmp_path / "c.onnx"
    E.contract_path(contract_only).write_text("{}")
    assert cli_main(["export", str(umaze), "--out", str(contract_only)]) == 2
    assert "c.onnx.json exists; pass --force" in capsys.readouterr().err

    assert cli_main(["export", str(tmp_path)]) == 2
    assert "is not a botorl run directory" in capsys.readouterr().err
    assert cli_main(["eval", str(umaze), "--policy", str(tmp_path / "none.onnx")]) == 2
    assert "no such model file" in capsys.readouterr().err
    assert cli_main(["eval", str(umaze), "--policy", str(taken), "--checkpoint", "pretrain-final"]) == 2
    assert "--policy and --checkpoint" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # tyro: one format
        cli_main(["export", str(umaze), "--format", "tflite"])


def test_graph_function_is_load_policy(umaze):
    """What the converter is handed, run by JAX: load_policy's actions on 256 dataset observations."""
    import botorl

    policy = botorl.load_policy(umaze)
    obs = _dataset_obs(umaze)
    got = np.asarray(E.policy_function(policy)(obs))
    assert got.shape == (256, 2) and got.dtype == np.float32
    assert np.abs(got - policy(obs)).max() <= 1e-6


def test_graph_function_maps_onto_the_env_box(umaze):
    """A task of one's own acts in its env's bounds: the graph's affine map equals action_to_env."""
    import botorl
    from botorl.envs.user import action_to_env

    policy = botorl.load_policy(umaze)
    unit = np.asarray(E.policy_function(policy)(_dataset_obs(umaze)))
    policy.action_low, policy.action_high = np.array([-0.1, 2.0]), np.array([0.1, 5.0])
    got = np.asarray(E.policy_function(policy)(_dataset_obs(umaze)))
    assert np.abs(got - action_to_env(unit, policy.action_low, policy.action_high)).max() <= 1e-6
    assert np.all(got[:, 1] >= 2.0) and np.all(got[:, 1] <= 5.0)


def test_contract_pieces():
    from gymnasium import spaces

    from botorl.configs.presets import make_preset

    space = spaces.Dict({"b": spaces.Box(-1, 1, (2,)), "a": spaces.Dict({"y": spaces.Box(0, np.inf, (1,)),
                                                                            "x": spaces.Box(-2, 2, (2, 2))})})
    layout = E.observation_layout(("a/x", "a/y", "b"), space)
    assert [(x["key"], x["shape"], x["offset"], x["size"]) for x in layout] == [
        ("a/x", [2, 2], 0, 4), ("a/y", [1], 4, 1), ("b", [2], 5, 2)]
    assert layout[1]["low"] == [0.0] and layout[1]["high"] == [None]  # JSON has no infinity
    assert [x["shape"] for x in E.observation_layout(("a/x", "b"), None)] == [None, None]
    assert E.observation_layout(None, space) is None
    assert E.contract_path("d/policy.onnx") == Path("d/policy.onnx.json")
    assert E.max_gap([[0.0, 1.0], [2.0, 3.0]], [[0.0, 1.0], [2.0, 3.5]]) == (0.5, 1)
    assert E.max_gap([[np.nan]], [[0.0]])[0] == float("inf")
    cfg = make_preset("pointmaze-umaze", "smoke", "boto")
    assert E.checkpoint_step(cfg, {"stage": "finetune", "step": None, "stage_done": True}) == cfg.online.steps
    assert E.checkpoint_step(cfg, {"stage": "pretrain", "step": 7, "stage_done": False}) == 7


# ------------------------------------------------------------------ with the extra
@pytest.fixture(scope="module")
def exported(umaze):
    pytest.importorskip("jax2onnx")
    pytest.importorskip("onnxruntime")
    res = _botorl("export", umaze)
    assert res.returncode == 0, res.stderr[-3000:]
    return umaze / "policy.onnx"


def test_export_writes_model_and_contract(exported, umaze):
    import hashlib

    import onnxruntime as ort

    import botorl

    contract = json.loads(E.contract_path(exported).read_text())
    assert contract["sha256"] == hashlib.sha256(exported.read_bytes()).hexdigest()
    assert contract["input"] == {"name": "observations", "shape": ["batch", 4], "dtype": "float32"}
    assert contract["output"] == {"name": "actions", "shape": ["batch", 2], "dtype": "float32"}
    cfg = json.loads((umaze / "config.json").read_text())
    assert (contract["task"], contract["method"], contract["seed"], contract["alpha"]) == (
        "pointmaze-umaze", "boto", 0, cfg["alpha"])
    assert contract["checkpoint"] == "finetune-final" and contract["step"] == cfg["online"]["steps"]
    assert contract["opset"] == E.OPSET and contract["botorl_version"] == botorl.__version__
    assert contract["action"]["low"] == [-1.0, -1.0] and contract["observation"]["layout"] is None
    v = contract["verification"]
    assert v["observations"] == 256 and v["source"] == "dataset" and v["max_abs_gap"] <= 1e-5

    # onnxruntime alone, a fresh session on the file: load_policy's actions on 256 dataset observations
    session = ort.InferenceSession(str(exported), providers=["CPUExecutionProvider"])
    assert [i.name for i in session.get_inputs()] == ["observations"]
    assert [o.name for o in session.get_outputs()] == ["actions"]
    obs = _dataset_obs(umaze)
    got = session.run(["actions"], {"observations": obs})[0]
    assert got.shape == (256, 2) and got.dtype == np.float32
    assert np.abs(got - botorl.load_policy(umaze)(obs)).max() <= 1e-5
    for b in (1, 7):  # the batch axis is dynamic
        assert np.abs(session.run(["actions"], {"observations": obs[:b]})[0] - got[:b]).max() <= 1e-6


def test_export_force_and_checkpoint(exported, umaze, tmp_path):
    out = tmp_path / "p.onnx"
    shutil.copy(exported, out)
    shutil.copy(E.contract_path(exported), E.contract_path(out))
    res = _botorl("export", umaze, "--out", out)
    assert res.returncode == 2 and "exists; pass --force" in res.stderr
    res = _botorl("export", umaze, "--checkpoint", "pretrain-final", "--force", "--out", out)
    assert res.returncode == 0, res.stderr[-2000:]
    again = json.loads(E.contract_path(out).read_text())
    assert again["checkpoint"] == "pretrain-final" and again["stage"] == "pretrain"
    assert again["step"] == json.loads((umaze / "config.json").read_text())["offline"]["steps"]
    assert again["sha256"] != json.loads(E.contract_path(exported).read_text())["sha256"]


def test_mismatch_exit_1_names_the_gap(umaze, tmp_path, monkeypatch, capsys):
    pytest.importorskip("jax2onnx")
    pytest.importorskip("onnxruntime")
    real = E.policy_function

    def off(policy):
        act = real(policy)
        return lambda obs: act(obs) + 1e-3

    monkeypatch.setattr(E, "policy_function", off)
    out = tmp_path / "off.onnx"
    assert cli_main(["export", str(umaze), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert re.search(r"max \|onnxruntime - load_policy\| = 0\.001 .* > 1e-05", err), err
    assert not out.exists() and not E.contract_path(out).exists()


def _eval_json(run: Path, name: str) -> dict:
    return json.loads((run / name).read_text())


def test_eval_policy_same_as_eval_umaze(exported, umaze):
    a = _botorl("eval", umaze, "--episodes", "3")
    b = _botorl("eval", umaze, "--episodes", "3", "--policy", exported)
    assert a.returncode == 0 and b.returncode == 0, a.stderr[-2000:] + b.stderr[-2000:]
    ckpt = _eval_json(umaze, "eval-finetune-final.json")
    onnx = _eval_json(umaze, "eval-policy-onnx.json")
    for k in ("episodes", "success", "return", "episode_length"):
        assert onnx[k] == ckpt[k], k


def test_eval_policy_same_episodes_step_by_step(exported, umaze):
    """The same episodes: the exported model's trajectories equal the checkpoint's (run_episodes
    with a recorder), so the equal success above is not two failures that happen to agree."""
    import botorl
    from botorl.envs.registry import get_task
    from botorl.pipeline.evaluation import run_episodes

    spec, policy, model = get_task("pointmaze-umaze"), botorl.load_policy(umaze), E.OnnxPolicy(exported)
    paths = {}
    for name, act in (("ckpt", policy), ("onnx", model)):
        seen = []
        env = spec.make_env(seed=10_000, evaluation=True)
        run_episodes(lambda o, act=act, seen=seen: (seen.append(o.copy()), act(o[0])[None])[1], [[env]], episodes=1,
                     success_mode=spec.success_mode, seeds=[200_000], max_steps=spec.max_episode_steps)
        paths[name] = np.concatenate(seen)
    assert paths["ckpt"].shape == paths["onnx"].shape and len(paths["ckpt"]) == spec.max_episode_steps
    assert np.abs(paths["ckpt"] - paths["onnx"]).max() <= 1e-3
    assert np.abs(paths["ckpt"][-1] - paths["ckpt"][0]).max() > 1e-2  # the point moved: a real trajectory


@pytest.fixture(scope="module")
def own(tmp_path_factory):
    """The docs' own task (Dict observations, actions in [-0.1, 0.1]) trained until it reaches its
    goal (1000 offline steps), exported."""
    pytest.importorskip("jax2onnx")
    pytest.importorskip("onnxruntime")
    d = tmp_path_factory.mktemp("own")
    shutil.copy(REPO / "examples" / "own_task.py", d / "mytask.py")
    res = subprocess.run([sys.executable, "mytask.py", "--save", "logged.npz"], cwd=d, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr
    run = d / "run"
    res = _botorl("run", "--env", "mytask:make_env", "--data.path", "logged.npz", "--env-max-steps", "50",
                  "--profile", "smoke", "--offline.steps", "1000", "--no-progress", "--no-tensorboard", "--out", run,
                  cwd=d)
    assert res.returncode == 0, res.stderr[-3000:]
    # a task of one's own is given again with --env (issue 39: nothing is imported from config.json)
    res = _botorl("export", run, "--out", d / "policy.onnx", "--env", "mytask:make_env", cwd=d)
    assert res.returncode == 0, res.stderr[-3000:]
    return d, run


@pytest.mark.slow  # ~75 s (a run of a task of one's own, then export); the shipped tasks' contract is tested above
def test_own_task_contract_and_eval_policy(own):
    d, run = own
    contract = json.loads((d / "policy.onnx.json").read_text())
    assert [(x["key"], x["offset"], x["size"]) for x in contract["observation"]["layout"]] == [
        ("goal", 0, 2), ("position", 2, 2)]
    assert contract["action"]["high"] == pytest.approx([0.1, 0.1])
    assert contract["verification"]["source"] == "dataset" and contract["verification"]["max_abs_gap"] <= 1e-5
    a = _botorl("eval", run, "--episodes", "6", "--env", "mytask:make_env", cwd=d)
    b = _botorl("eval", run, "--episodes", "6", "--policy", d / "policy.onnx", "--env", "mytask:make_env", cwd=d)
    assert a.returncode == 0 and b.returncode == 0, a.stderr[-2000:] + b.stderr[-2000:]
    ckpt, onnx = _eval_json(run, "eval-finetune-final.json"), _eval_json(run, "eval-policy-onnx.json")
    assert ckpt["success"] > 0.5  # the policy reaches the goal, so equal success is a real check
    for k in ("success", "return", "episode_length"):
        assert onnx[k] == pytest.approx(ckpt[k], abs=1e-9), k


def test_eval_policy_refuses_another_run_or_a_changed_model(own, exported, umaze):
    d, run = own
    res = _botorl("eval", umaze, "--policy", d / "policy.onnx")
    assert res.returncode == 2 and "is a policy of task 'mytask.make_env'" in res.stderr
    changed = d / "changed.onnx"
    shutil.copy(exported, changed)
    contract = json.loads(E.contract_path(exported).read_text())
    E.contract_path(changed).write_text(json.dumps({**contract, "sha256": "0" * 64}))
    res = _botorl("eval", umaze, "--policy", changed)
    assert res.returncode == 2 and "sha256 differs" in res.stderr


def test_docs_loop_runs_without_botorl(own):
    """The docs page's loop, with botorl and JAX made unimportable, drives the env to the goal."""
    d, _ = own
    page = (REPO / "docs" / "deploy.md").read_text()
    loop = next(b for b in re.findall(r"```python\n(.*?)```", page, re.S) if "import onnxruntime" in b)
    assert len(loop.strip().splitlines()) <= 25
    guard = "import sys\nfor m in ('botorl', 'jax', 'flax'):\n    sys.modules[m] = None\n"
    res = subprocess.run([sys.executable, "-c", guard + loop], cwd=d, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert re.search(r"success 1\.0 steps \d+", res.stdout), res.stdout


# ------------------------------------------------------------------ issue 39: a model is checked before it runs
def _onnx_model(path: Path, nodes, initializers, out_dim: int, graphs_in=()) -> Path:
    from onnx import TensorProto, helper, numpy_helper

    graph = helper.make_graph(
        nodes, "policy", [helper.make_tensor_value_info(E.INPUT_NAME, TensorProto.FLOAT, ["batch", 4])],
        [helper.make_tensor_value_info(E.OUTPUT_NAME, TensorProto.FLOAT, ["batch", out_dim])],
        [numpy_helper.from_array(np.asarray(v), k) for k, v in initializers.items()])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    path.write_bytes(model.SerializeToString())
    return path


def test_eval_policy_checks_the_model_before_and_while_it_runs(umaze, exported, tmp_path, capsys):
    """A model whose output width differs, that fails at run time, that gives NaN, that loops 2**62
    times, or whose contract's shapes or bounds disagree: exit 2 with a message, never a traceback
    or a hang."""
    from onnx import TensorProto, helper

    mm = lambda w: [helper.make_node("MatMul", [E.INPUT_NAME, "w"], [E.OUTPUT_NAME])]  # noqa: E731
    wide = _onnx_model(tmp_path / "wide.onnx", mm(None), {"w": np.zeros((4, 3), np.float32)}, 3)
    # a column index past the observation's 4: its shapes are sound (issue 51 bounds them before the
    # model runs), onnxruntime fails when it gathers
    fails = _onnx_model(tmp_path / "fails.onnx",
                        [helper.make_node("Gather", [E.INPUT_NAME, "s"], [E.OUTPUT_NAME], axis=1)],
                        {"s": np.array([0, 9], np.int64)}, 2)
    nan = _onnx_model(tmp_path / "nan.onnx", mm(None), {"w": np.full((4, 2), np.nan, np.float32)}, 2)
    body = helper.make_graph([helper.make_node("Identity", ["c"], ["c_out"])], "body",
                             [helper.make_tensor_value_info("i", TensorProto.INT64, []),
                              helper.make_tensor_value_info("c", TensorProto.BOOL, [])],
                             [helper.make_tensor_value_info("c_out", TensorProto.BOOL, [])])
    loop = _onnx_model(tmp_path / "loop.onnx",
                       [helper.make_node("Loop", ["n", "cond"], [], body=body),
                        helper.make_node("MatMul", [E.INPUT_NAME, "w"], [E.OUTPUT_NAME])],
                       {"n": np.array(2**62, np.int64), "cond": np.array(True), "w": np.zeros((4, 2), np.float32)}, 2)
    for model, words in ((wide, "gives 3 action values"), (fails, "failed on observations"),
                         (nan, "with NaN/inf"), (loop, "control-flow operator(s) Loop")):
        assert cli_main(["eval", str(umaze), "--policy", str(model), "--episodes", "1"]) == 2, model
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err, (model, err)
    # a contract that agrees in sha256 but not in shapes or bounds
    contract = json.loads(E.contract_path(exported).read_text())
    for key, value, words in ((("action", "high"), [2.0, 2.0], "action high [2.0, 2.0] in the contract"),
                              (("output", "shape"), ["batch", 3], "output width ['batch', 3] in the contract")):
        copy = tmp_path / f"{key[0]}.onnx"
        shutil.copy(exported, copy)
        c = json.loads(json.dumps(contract))
        c[key[0]][key[1]] = value
        E.contract_path(copy).write_text(json.dumps(c))
        assert cli_main(["eval", str(umaze), "--policy", str(copy), "--episodes", "1"]) == 2
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err, err
    fifo = tmp_path / "fifo.onnx"
    import os

    os.mkfifo(fifo)
    assert cli_main(["eval", str(umaze), "--policy", str(fifo)]) == 2
    assert "not a regular file" in capsys.readouterr().err

"""Sizes before work, types and ranges at the edge (issue 51): a file is sized before it is
hashed or read, every archive member and HDF5 dataset is bounded whatever its name, an ONNX
graph is bounded before it runs, a restored env cannot make one step run for hours, evaluation
and sweep inputs have caps; every config field has its type (resealed or not, no number beyond a
float), every number flag its range, every dataset field a numeric dtype. Each case is exit 2 (a
BotorlError) within seconds, never a traceback, a hang or hours of work; each failed before
issue 51.

The Hypothesis strategies at the end draw datasets (dtypes, member names, declared sizes), CLI
numbers (every ranged flag, out of range) and run-directory JSON numbers (beyond a float)."""

from __future__ import annotations

import dataclasses
import io
import json
import math
import os
import subprocess
import time
import typing
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from botorl.cli import main as botorl_main
from botorl.errors import BotorlError, ConfigError, DataFormatError, Range, check_ranges

RUN_CONFIG = None  # a smoke run's config.json (built once: the schema imports JAX)


def _config_dict() -> dict:
    global RUN_CONFIG
    if RUN_CONFIG is None:
        from botorl.configs.build import build_config
        from botorl.configs.schema import to_dict

        RUN_CONFIG = to_dict(build_config(["--task", "pointmaze-umaze", "--profile", "smoke"]))
    return json.loads(json.dumps(RUN_CONFIG))


def _sparse(path: Path, size: str = "1T") -> Path:
    subprocess.run(["truncate", "-s", size, str(path)], check=True)
    return path


def _npy(array_or_header: np.ndarray | dict) -> bytes:
    buf = io.BytesIO()
    if isinstance(array_or_header, dict):
        np.lib.format.write_array_header_1_0(buf, array_or_header)
    else:
        np.save(buf, array_or_header)
    return buf.getvalue()


# ============================================================================ 1. sizes before work
@pytest.mark.timeout(60)
def test_a_sparse_terabyte_is_refused_before_it_is_hashed(tmp_path):
    from botorl.data.safe import fingerprint
    from botorl.io import file_sha256
    from botorl.pipeline.checkpoint import CheckpointCorrupt, CheckpointManager

    big = _sparse(tmp_path / "data.hdf5")
    t = time.monotonic()
    with pytest.raises(DataFormatError, match=r"1,099,511,627,776 bytes.*more than botorl reads"):
        fingerprint(big)  # data.path: hashed for every checkpoint's identity
    with pytest.raises(ValueError, match="1,099,511,627,776 bytes"):
        file_sha256(big, 1 << 30)
    # a checkpoint whose manifest agrees with a 1 TB agent.ckpt (a forged manifest)
    ck = tmp_path / "checkpoints" / "pretrain-final"
    ck.mkdir(parents=True)
    _sparse(ck / "agent.ckpt")
    (ck / "state.json").write_text(json.dumps({"stage": "pretrain"}))
    (ck / "MANIFEST.json").write_text(json.dumps({"name": "pretrain-final", "seq": 1, "files": {
        "agent.ckpt": {"size": 1 << 40, "sha256": "0" * 64}}}))
    with pytest.raises(CheckpointCorrupt, match="1,099,511,627,776 bytes"):
        CheckpointManager(tmp_path / "checkpoints").file("pretrain-final", "agent.ckpt")
    assert time.monotonic() - t < 10  # hashing 1 TB takes hours


def _zip(path: Path, members: dict[str, bytes], *, zeros: dict[str, tuple[dict, int]] | None = None) -> Path:
    """A .npz-like zip: ``members`` as given, ``zeros`` as an npy header then that many zero bytes,
    deflated (a few hundred KB that inflate to hundreds of MB)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in members.items():
            z.writestr(name, data)
        for name, (header, n) in (zeros or {}).items():
            with z.open(name, "w", force_zip64=True) as f:
                f.write(_npy(header))
                chunk = b"\0" * (1 << 22)
                for _ in range(n // len(chunk)):
                    f.write(chunk)
    return path


@pytest.mark.timeout(60)
def test_every_npz_member_is_bounded_whatever_its_name(tmp_path):
    from botorl.data.safe import INFLATE_FREE, check_npz
    from botorl.pipeline.checkpoint import CheckpointCorrupt, load_npz

    plain = _npy(np.zeros(4, np.float32))
    # np.load reads a member without the .npy suffix as an array too, unchecked
    nameless = _zip(tmp_path / "nameless.npz", {"observations.npy": plain, "rewards": plain})
    with pytest.raises(DataFormatError, match="'rewards' is not a .npy array"):
        check_npz(nameless)
    # a deflated run of zeros that declares more than INFLATE_FREE: a compression bomb
    n = INFLATE_FREE + (16 << 20)
    bomb = _zip(tmp_path / "bomb.npz", {}, zeros={"observations.npy": (
        {"descr": "<f4", "fortran_order": False, "shape": (n // 4,)}, n)})
    assert bomb.stat().st_size < n // 100
    for check, err in ((check_npz, DataFormatError), (load_npz, CheckpointCorrupt)):  # a user's data; buffer.npz
        with pytest.raises(err, match="compression bomb"):
            check(bomb)
    # control: what np.savez writes is read
    np.savez(tmp_path / "good.npz", observations=np.zeros((3, 2), np.float32))
    assert check_npz(tmp_path / "good.npz") == {"observations": ((3, 2), np.dtype("<f4"))}


@pytest.mark.timeout(60)
def test_hdf5_datasets_are_bounded_and_links_lead_somewhere(tmp_path, capsys):
    import h5py

    def d4rl(path: Path, extra=None) -> Path:
        with h5py.File(path, "w") as f:
            for k, v in (("observations", np.zeros((8, 3), np.float32)), ("actions", np.zeros((8, 2), np.float32)),
                         ("rewards", np.zeros(8, np.float32)), ("terminals", np.zeros(8, bool))):
                f.create_dataset(k, data=v)
            if extra:
                extra(f)
        return path

    cases = {
        # gzip-chunked, never written: 400 MB declared in a file of a few KB
        "bomb": (lambda f: f.create_dataset("infos/goal", shape=(10**8,), dtype="f4", chunks=(10**5,),
                                            compression="gzip"), "compression bomb"),
        "self": (lambda f: f.__setitem__("loop", h5py.SoftLink("/loop")), "leads nowhere"),
        "nothing": (lambda f: f.__setitem__("gone", h5py.SoftLink("/not/there")), "leads nowhere"),
    }
    for name, (extra, needle) in cases.items():
        assert botorl_main(["data", "info", str(d4rl(tmp_path / f"{name}.hdf5", extra))]) == 2
        err = capsys.readouterr().err
        assert needle in err and "Traceback" not in err, (name, err)
    assert botorl_main(["data", "info", str(d4rl(tmp_path / "good.hdf5"))]) == 0  # control


@pytest.mark.timeout(60)
def test_dataset_fields_must_be_numbers(tmp_path):
    import h5py

    from botorl.data.dataset import Dataset
    from botorl.data.loaders import load_d4rl_hdf5
    from botorl.data.user import from_arrays
    from botorl.envs.user import UserTask

    n = 6
    good = {"observations": np.zeros((n, 3), np.float32), "actions": np.zeros((n, 2), np.float32),
            "rewards": np.zeros(n, np.float32), "next_observations": np.zeros((n, 3), np.float32),
            "terminals": np.zeros(n, bool)}
    task = UserTask(obs_keys=None, obs_dim=3, action_dim=2, action_low=(-1.0, -1.0), action_high=(1.0, 1.0),
                    success_key=None)
    for field, bad in (("rewards", np.array([b"1"] * n)), ("observations", np.zeros((n, 3), np.complex64)),
                       ("terminals", np.array(["0"] * n)), ("actions", np.zeros((n, 2), object))):
        with pytest.raises(DataFormatError, match=f"{field} has dtype"):
            from_arrays({**good, field: bad}, task, source="crafted")
        with pytest.raises(DataFormatError, match=f"{field} has dtype"):
            Dataset(*(({**good, field: bad})[k] for k in ("observations", "actions", "rewards", "next_observations",
                                                          "terminals")))
    assert len(from_arrays(good, task, source="crafted")) == n  # control
    with h5py.File(tmp_path / "complex.hdf5", "w") as f:  # a D4RL file: read as stored, then checked
        for k, v in {**good, "observations": np.ones((n, 3), np.complex64)}.items():
            f.create_dataset(k, data=v)
    with pytest.raises(DataFormatError, match="observations has dtype complex64"):
        load_d4rl_hdf5(tmp_path / "complex.hdf5")


def _onnx_model(nodes, initializers=(), width: int = 4):
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper

    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("observations", TensorProto.FLOAT, ["B", width])],
                              [helper.make_tensor_value_info("actions", TensorProto.FLOAT, None)], list(initializers))
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]).SerializeToString(), onnx


@pytest.mark.timeout(60)
def test_onnx_graphs_are_bounded_before_they_run():
    from onnx import helper, numpy_helper

    from botorl.pipeline.export import check_graph

    w = numpy_helper.from_array(np.zeros((3000, 3000), np.float32), "W")
    chain = [helper.make_node("MatMul", ["W", "W"], ["m0"])]
    chain += [helper.make_node("MatMul", [f"m{i - 1}", "W"], [f"m{i}"]) for i in range(1, 40)]
    chain += [helper.make_node("ReduceSum", ["m39"], ["s"], keepdims=0),
              helper.make_node("Add", ["observations", "s"], ["actions"])]
    shape = numpy_helper.from_array(np.array([1_500_000_000], np.int64), "shape")
    zero, one = (numpy_helper.from_array(np.array(v, np.float32), n) for v, n in ((0, "zero"), (1, "one")))
    cases = {
        "40 MatMuls of 3000 x 3000": (chain, [w], "MatMul/Gemm FLOPs"),
        "ConstantOfShape of 6 GB": ([helper.make_node("ConstantOfShape", ["shape"], ["c"]),
                                     helper.make_node("ReduceSum", ["c"], ["s"], keepdims=0),
                                     helper.make_node("Add", ["observations", "s"], ["actions"])], [shape], "values"),
        "Range sized by the observation": ([helper.make_node("ReduceMax", ["observations"], ["top"], keepdims=0),
                                            helper.make_node("Range", ["zero", "top", "one"], ["r"]),
                                            helper.make_node("ReduceSum", ["r"], ["s"], keepdims=0),
                                            helper.make_node("Add", ["observations", "s"], ["actions"])],
                                           [zero, one], "depends on the observations"),
        "a convolution": ([helper.make_node("Conv", ["observations", "W"], ["actions"])], [w], "no botorl policy has"),
    }
    for what, (nodes, inits, needle) in cases.items():
        model, _ = _onnx_model(nodes, inits)
        t = time.monotonic()
        with pytest.raises(ConfigError, match=needle):
            check_graph(model, what)
        assert time.monotonic() - t < 20, what
    w4 = numpy_helper.from_array(np.zeros((4, 2), np.float32), "W4")  # control: one small layer
    model, _ = _onnx_model([helper.make_node("MatMul", ["observations", "W4"], ["h"]),
                            helper.make_node("Tanh", ["h"], ["actions"])], [w4])
    check_graph(model, "a small policy")


@pytest.mark.timeout(120)
def test_a_restored_env_cannot_make_one_step_run_for_hours():
    from botorl.envs.registry import get_task
    from botorl.envs.state import get_env_state, set_env_state

    spec = get_task("pointmaze-umaze")
    env = spec.make_env(seed=0)
    env.reset(seed=3)
    env.step(np.zeros(2, np.float32))
    state = json.loads(json.dumps(get_env_state(env)))
    layer = next(v for k, v in state["layers"].items() if "frame_skip" in v["attrs"])
    layer["attrs"]["frame_skip"] = 10**9
    fresh = spec.make_env(seed=0)
    with pytest.raises(ValueError, match="frame_skip holds 1,000,000,000"):
        set_env_state(fresh, state, 300_000)  # late in a run: a counter over episodes may reach its steps
    layer["attrs"]["frame_skip"] = 1  # control: the state as saved restores
    set_env_state(fresh, state, 300_000)
    for e in (env, fresh):
        e.close()


def test_evaluation_sizes_have_caps_a_small_machine_finishes():
    from botorl.configs.resolve import BOUNDS, check_bounds
    from botorl.configs.schema import RunConfig, from_dict

    for field, value in (("episodes", 1_000_000), ("num_envs", 1024), ("episodes", BOUNDS["eval.episodes"] + 1)):
        cfg = _config_dict()
        cfg["eval"][field] = value
        with pytest.raises(ConfigError, match=f"eval.{field}.*at most"):
            check_bounds(from_dict(RunConfig, cfg))
    assert BOUNDS["eval.episodes"] <= 1_000 and BOUNDS["eval.num_envs"] <= 64


@pytest.mark.timeout(60)
def test_sweep_inputs_are_regular_files_of_bounded_size(tmp_path, capsys):
    fifo = tmp_path / "grid.yaml"
    os.mkfifo(fifo)
    big = _sparse(tmp_path / "big.yaml", "2M")
    for args in (["sweep", "--out", str(tmp_path / "s"), "--grid", str(fifo)],
                 ["sweep", "--out", str(tmp_path / "s"), "--grid", "/dev/zero"],
                 ["sweep", "--out", str(tmp_path / "s"), "--grid", str(big)],
                 ["report", "--pairs-from", str(fifo), "--out", str(tmp_path / "r")],
                 ["report", "--pairs-from", "/dev/zero", "--out", str(tmp_path / "r")]):
        assert botorl_main(args) == 2, args
        err = capsys.readouterr().err
        assert ("not a regular file" in err or "more than" in err) and "Traceback" not in err, (args, err)
    assert not (tmp_path / "s").exists() and not (tmp_path / "r").exists()


# ============================================================================ 2. types and ranges at the edge
RESEALED = {  # a run directory's config.json, edited: (where, value, what the message names)
    "a seed as a string": (("seed",), "0", "seed"),
    "seeds as an integer": (("seeds",), 5, "seeds"),
    "data.path a list": (("data", "path"), [1], "data.path"),
    "data.path a number": (("data", "path"), 3, "data.path"),
    "buffer_capacity a word": (("online", "buffer_capacity"), "x", "online.buffer_capacity"),
    "target_entropy a word": (("online", "sac", "target_entropy"), "abc", "online.sac.target_entropy"),
    "weight_fn a dict": (("boto", "weight_fn"), {"a": 1}, "boto.weight_fn"),
    "a learning rate null": (("online", "sac", "actor_lr"), None, "online.sac.actor_lr"),
    "a method not in the table": (("method",), "ppo", "method"),
    "NaN reward": (("offline", "mc_sparse_negative_reward"), math.nan, "offline.mc_sparse_negative_reward"),
    "more min-critics than critics": (("offline", "cql", "num_min_critics"), 100, "num_min_critics"),
    "widths within the per-layer cap": (("network", "critic_hidden_dims"), [65536, 65536], "hidden-layer weights"),
    "an empty --out": (("out",), "", "--out is empty"),
    "a 5,000-character --out": (("out",), "/tmp/" + "a" * 5000, "bytes long"),
}


def _crafted_run(root: Path, cfg: dict, text: str | None = None) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    (root / "config.json").write_text(json.dumps(cfg) if text is None else text)
    return root


@pytest.mark.parametrize("case", sorted(RESEALED))
def test_a_resealed_config_is_typed_field_by_field(tmp_path, case):
    from botorl.pipeline.policy import read_run

    where, value, needle = RESEALED[case]
    cfg = _config_dict()
    node = cfg
    for k in where[:-1]:
        node = node[k]
    node[where[-1]] = value
    run = _crafted_run(tmp_path / "run", cfg)
    with pytest.raises(ConfigError, match=needle.replace(".", r"\.")):
        read_run(run, validate=True)
    # the same file given as `botorl run --config FILE` (a sweep's trial)
    with pytest.raises((ConfigError, SystemExit)) as err:
        from botorl.configs.build import build_config

        build_config(["--config", str(run / "config.json")])
    assert not isinstance(err.value, SystemExit) or err.value.code == 2


def test_resume_and_eval_refuse_a_mistyped_config_with_exit_2(tmp_path, capsys):
    cfg = _config_dict()
    cfg["online"]["buffer_capacity"] = "x"
    run = _crafted_run(tmp_path / "run", cfg)
    for cmd in (["eval", str(run)], ["resume", str(run)], ["export", str(run)]):
        assert botorl_main(cmd) == 2, cmd
        err = capsys.readouterr().err
        assert "online.buffer_capacity" in err and "Traceback" not in err, err


def test_cli_flags_refuse_values_outside_their_range(tmp_path, capsys):
    for args, needle in ((["sweep", "--out", str(tmp_path / "s"), "--workers", "-1"], "--workers"),
                         (["sweep", "--out", str(tmp_path / "s"), "--population-size", "-5"], "--population-size"),
                         (["sweep", "--out", str(tmp_path / "s"), "--population-size", str(10**9)], "--population-size"),
                         (["report", str(tmp_path), "--grid-points", "0"], "--grid-points"),
                         (["report", str(tmp_path), "--grid-points", "-3"], "--grid-points"),
                         (["report", str(tmp_path), "--seed", "-1"], "--seed"),
                         (["run", "--profile", "smoke", "--offline.mc-sparse-negative-reward", "nan"],
                          "mc_sparse_negative_reward"),
                         (["run", "--profile", "smoke", "--offline.cql.num-min-critics", "100"], "num_min_critics")):
        assert botorl_main(args) == 2, args
        err = capsys.readouterr().err
        assert needle in err and "Traceback" not in err, (args, err)
    assert not (tmp_path / "s").exists()


@pytest.mark.parametrize("out", ["", "/proc/botorl-out", "FILE", "/tmp/" + "a" * 5000],
                         ids=["empty", "under-proc", "a-file", "5000-chars"])
def test_out_is_a_folder_botorl_can_make(tmp_path, capsys, out):
    (tmp_path / "FILE").write_text("keep")
    out = str(tmp_path / "FILE") if out == "FILE" else out
    for cmd in (["run", "--profile", "smoke", "--out", out], ["report", str(tmp_path), "--out", out],
                ["sweep", "--out", out, "--tasks", "pointmaze-umaze", "--methods", "boto", "--seeds", "0", "--dry-run"]):
        assert botorl_main(cmd) == 2, cmd
        err = capsys.readouterr().err
        assert "--out" in err and "Traceback" not in err, (cmd, err)
    assert (tmp_path / "FILE").read_text() == "keep"


def test_csv_a_lock_folder_and_numbers_beyond_a_float_are_exit_2(tmp_path):
    from botorl.experiments.runs import find_runs
    from botorl.io import UnsafeFileError, read_json_bounded
    from botorl.pipeline.rundir import CsvLog, RunLock

    run = tmp_path / "run"
    run.mkdir()
    (run / "summary.json").write_text('{"task": "t", "method": "wsrl", "status": "finished", "success_final": 1e400}')
    (run / "config.json").write_text(json.dumps({"task": "t", "method": "wsrl", "seed": 10**400}))
    (run / "eval.csv").write_text("env_step,success\n0," + "9" * 200_000 + "\n")  # over the csv module's field limit
    runs, skipped = find_runs([tmp_path])
    assert not runs and "beyond a float" in skipped[0].reason
    for name in ("summary.json", "config.json"):
        with pytest.raises(ValueError, match="beyond a float"):
            read_json_bounded(run / name)
    (run / "summary.json").write_text('{"task": "t", "method": "wsrl", "status": "finished"}')
    (run / "config.json").write_text('{"task": "t", "method": "wsrl", "seed": 0}')
    runs, skipped = find_runs([tmp_path])
    assert not runs and "eval.csv" in skipped[0].reason and "field larger than field limit" in skipped[0].reason
    with pytest.raises(UnsafeFileError, match="not CSV botorl wrote"):
        CsvLog(run / "eval.csv").rows()
    (run / ".lock").mkdir()
    with pytest.raises(UnsafeFileError, match="is a directory"):
        RunLock(run).acquire()


# ============================================================================ 3. strategies
_DTYPES = st.sampled_from(["<f4", "<f8", "<i4", "|b1", "|u1", "|S3", "<U2", "<c8", "<c16", "<M8[s]", "<m8[s]"])


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(dtype=_DTYPES, field=st.sampled_from(["observations", "actions", "rewards", "terminals"]))
def test_any_dtype_is_a_dataset_or_a_reason(dtype, field):
    from botorl.data.dataset import Dataset

    n = 4
    arrays = {"observations": np.zeros((n, 3)), "actions": np.zeros((n, 2)), "rewards": np.zeros(n),
              "next_observations": np.zeros((n, 3)), "terminals": np.zeros(n, bool)}
    arrays[field] = np.zeros(arrays[field].shape, np.dtype(dtype))
    try:
        ds = Dataset(*(arrays[k] for k in ("observations", "actions", "rewards", "next_observations", "terminals")))
    except DataFormatError as err:
        assert np.dtype(dtype).kind not in "biuf" and field in str(err)
    else:
        assert np.dtype(dtype).kind in "biuf" and len(ds) == n


_MEMBER = st.one_of(st.sampled_from(["observations.npy", "rewards", "x.npy/", "../up.npy", "a/b.npy", "a.NPY"]),
                    st.text(st.characters(min_codepoint=32, max_codepoint=0x2FF), min_size=1, max_size=12))


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(names=st.lists(_MEMBER, min_size=1, max_size=3, unique=True),
       shape=st.lists(st.integers(0, 2**40), min_size=1, max_size=3), dtype=_DTYPES, body=st.integers(0, 64))
def test_any_npz_is_read_from_its_headers_or_refused(tmp_path_factory, names, shape, dtype, body):
    """A member's name, its declared shape (up to 2**40 rows) and dtype, and how many bytes
    follow its header: check_npz answers from the headers at once, never inflating a member."""
    from botorl.data.safe import check_npz

    path = tmp_path_factory.mktemp("npz") / "d.npz"
    header = _npy({"descr": np.dtype(dtype).str, "fortran_order": False, "shape": tuple(shape)})
    _zip(path, {n: header + b"\0" * body for n in names})
    t = time.monotonic()
    try:
        got = check_npz(path)
    except DataFormatError:
        pass
    else:  # accepted: only .npy members whose header fits what follows it
        assert all(n.endswith(".npy") for n in names)
        assert all(int(np.prod(s, dtype=object)) * d.itemsize <= body for s, d in got.values())
    assert time.monotonic() - t < 5


def _ranged_fields():
    from botorl.benchmarks.suite import BenchConfig
    from botorl.boto.bandit import BanditConfig
    from botorl.data.cli import Generate, Info
    from botorl.envs.cli import CheckConfig
    from botorl.experiments.cli import ReportArgs, SweepArgs
    from botorl.experts.ant_train import AntTrainConfig
    from botorl.pipeline.cli import EvalArgs

    out = []
    for cls, required in ((SweepArgs, {"out": "s"}), (ReportArgs, {"dirs": ("d",)}), (EvalArgs, {"dir": "d"}),
                          (CheckConfig, {"task": "t"}), (BanditConfig, {}), (BenchConfig, {}), (Generate, {"task": "t"}),
                          (Info, {"target": "t"}), (AntTrainConfig, {})):
        hints = typing.get_type_hints(cls, include_extras=True)
        for f in dataclasses.fields(cls):
            bound = next((m for m in getattr(hints[f.name], "__metadata__", ()) if isinstance(m, Range)), None)
            if bound is not None:
                out.append((cls, required, f.name, bound))
    return out


RANGED = _ranged_fields()


def test_every_command_number_flag_has_a_range():
    """The flags the issue found unbounded carry a Range (and the strategy below draws them all)."""
    have = {(cls.__name__, name) for cls, _, name, _ in RANGED}
    assert {("SweepArgs", "workers"), ("SweepArgs", "population_size"), ("ReportArgs", "grid_points"),
            ("ReportArgs", "seed"), ("EvalArgs", "episodes"), ("Generate", "steps")} <= have


@settings(max_examples=150, deadline=None)
@given(field=st.sampled_from(RANGED), data=st.data())
def test_any_out_of_range_number_flag_is_refused_naming_it(field, data):
    cls, required, name, bound = field
    is_float = any(isinstance(m, float) for m in (bound.lo, bound.hi))
    below = st.integers(max_value=math.ceil(bound.lo) - 1) if not is_float else st.floats(max_value=bound.lo,
                                                                                          exclude_max=True)
    above = st.integers(min_value=math.floor(bound.hi) + 1) if not is_float else st.floats(min_value=bound.hi,
                                                                                           exclude_min=True)
    value = data.draw(st.one_of(below, above, st.just(math.nan)) if is_float else st.one_of(below, above))
    args = cls(**{**required, name: value})
    with pytest.raises(ConfigError, match="--" + name.rstrip("_").replace("_", "-")):
        check_ranges(args)
    check_ranges(cls(**{**required, name: data.draw(st.integers(math.ceil(bound.lo), math.floor(bound.hi)))}))


_BEYOND_FLOAT = st.one_of(
    st.integers(309, 1000).map(lambda k: "1" + "0" * k),  # an integer literal past 1.8e308
    st.integers(309, 10**5).map(lambda e: f"1e{e}"), st.integers(309, 10**5).map(lambda e: f"-2.5E+{e}"))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(number=_BEYOND_FLOAT, name=st.sampled_from(["summary.json", "config.json"]),
       key=st.sampled_from(["seed", "alpha", "success_final", "task", "online"]))
def test_any_number_beyond_a_float_in_a_run_file_is_refused(tmp_path_factory, number, name, key):
    from botorl.experiments.runs import find_runs

    root = tmp_path_factory.mktemp("runs")
    run = root / "run"
    run.mkdir()
    files = {"summary.json": '{"task": "t", "method": "wsrl", "seed": 0, "status": "finished"}',
             "config.json": '{"task": "t", "method": "wsrl", "seed": 0}'}
    files[name] = files[name][:-1] + f', "{key}": {number}}}'
    for n, text in files.items():
        (run / n).write_text(text)
    (run / "eval.csv").write_text("env_step,success\n0,1\n")
    runs, skipped = find_runs([root])
    if name == "summary.json":
        assert not runs and "beyond a float" in skipped[0].reason
    else:  # config.json is optional (older runs): unreadable, the run is read from its summary alone
        assert [(r.task, r.seed) for r in runs] == [("t", 0)]

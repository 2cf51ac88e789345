"""A run's policy as an ONNX model with its contract (``botorl export``, ``botorl.export_policy``).

The graph is ``load_policy``'s deterministic chain after ``flatten_obs`` (the caller flattens a
Dict observation in the contract's ``observation.layout`` order), traced by jax2onnx from the
agent's own ``eval_fn``; it is written only once onnxruntime's actions match ``load_policy``'s
(docs/deploy.md). ``OnnxPolicy`` runs an exported model (``botorl eval RUN --policy FILE``).

JAX (and the runner and the evaluation, which import it) is imported inside the functions that
need it: botorl.api imports this module, and the API's names stay free of it (tests/test_own_task.py).
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import logging
import os
import stat
import sys
from pathlib import Path
from typing import Any

import numpy as np

from botorl import __version__ as botorl_version
from botorl.configs.custom import ensure_task, register_given
from botorl.envs.registry import get_task
from botorl.envs.user import action_from_env, is_unit_box
from botorl.envs.wrappers import TaskEnv
from botorl.errors import BotorlError, ConfigError
from botorl.io import atomic_write_bytes, atomic_write_json, file_sha256, read_bounded_bytes
from botorl.jaxsetup import setup_jax
from botorl.pipeline.checkpoint import CheckpointManager, checkpoint_step
from botorl.pipeline.policy import check_checkpoint, load_policy, read_run, task_io
from botorl.pipeline.provenance import package_version
from botorl.pipeline.rundir import read_json

INSTALL = 'pip install "botorl[export]"'
OPSET = 17  # LayerNormalization's first opset; onnxruntime >= 1.13 runs it (robots' runtimes lag)
TOLERANCE = 1e-5
VERIFY_ROWS = 256
INPUT_NAME = "observations"
OUTPUT_NAME = "actions"
FORMATS = ("onnx",)


class MissingExportDependency(BotorlError):
    """onnx, onnxruntime or jax2onnx is not installed (exit 2 with the install line)."""


class ExportMismatch(BotorlError):
    """The written model does not act as ``load_policy`` does (exit 1)."""

    exit_code = 1


def require(*modules: str) -> dict[str, Any]:
    """Import the export extra's ``modules`` (``onnx``, ``onnxruntime``, ``jax2onnx``) or say how to install them."""
    # jax2onnx logs a traceback for each of its plugins whose library (equinox, dm-pix) is absent;
    # botorl's actor needs none of them
    logging.getLogger("jax2onnx").setLevel(logging.ERROR)
    got, missing = {}, []
    for name in modules:
        try:
            got[name] = importlib.import_module(name)
        except ImportError:
            missing.append(name)
    if missing:
        raise MissingExportDependency(f"{', '.join(missing)} {'is' if len(missing) == 1 else 'are'} not installed; "
                                      f"exporting and running an ONNX policy need the export extra: {INSTALL}")
    return got


def contract_path(model: str | Path) -> Path:
    """The contract beside a model: ``FILE.json`` (``policy.onnx`` -> ``policy.onnx.json``)."""
    model = Path(model)
    return model.with_name(model.name + ".json")


# ------------------------------------------------------------------ the run
def check_replaceable(p: Path, force: bool) -> None:
    """ConfigError unless ``p`` may be written: absent, or (``force``) a regular file. A link, a
    device, a FIFO or a folder is never replaced (``--out /dev/null --force`` as root would
    otherwise put a regular file in its place)."""
    try:
        st = p.lstat()
    except FileNotFoundError:
        return
    except OSError as err:
        raise ConfigError(f"--out: {p} cannot be looked at ({err.strerror}); give another --out.") from None
    if stat.S_ISDIR(st.st_mode):
        raise ConfigError(f"--out {p} is a folder; give a file name such as {p / 'policy.onnx'}.")
    if not stat.S_ISREG(st.st_mode):
        kind = "a link" if stat.S_ISLNK(st.st_mode) else "not a regular file (a device, FIFO or socket)"
        raise ConfigError(f"--out: {p} is {kind}; botorl export replaces only regular files. Give another --out.")
    if not force:
        raise ConfigError(f"{p} exists; pass --force (force=True) to overwrite it, or give another --out.")


def check_writable_folder(out: Path) -> None:
    """ConfigError, before any work, when ``out``'s folder cannot hold the model (``/proc/self``,
    a read-only or missing parent that cannot be made)."""
    parent = out.parent
    probe = next((p for p in (parent, *parent.parents) if p.exists()), Path("."))  # the nearest that exists
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK) or str(probe.resolve()).startswith(("/proc", "/sys")):
        raise ConfigError(f"--out {out}: its folder {parent} cannot be written; give a file in a folder you can write.")


def check_exportable(run, checkpoint: str | None) -> None:
    """ConfigError when no checkpoint is named and no stage has finished yet (only mid-stage ones)."""
    ckpt = CheckpointManager(run.checkpoints)
    if checkpoint is None and not any(_stage_done(ckpt, n) for n in ckpt.names()):
        there = [n for n in ckpt.names() if ckpt.exists(n)]
        more = (f" Its checkpoints ({', '.join(there)}) are mid-stage; name one with --checkpoint NAME to export it "
                f"anyway." if there else "")
        raise ConfigError(f"{run.root} has no finished stage yet, so no policy to export; wait for the first stage "
                          f"(pre-training) to finish.{more}")


def _stage_done(ckpt, name: str) -> bool:
    try:
        return bool(ckpt.state(name).get("stage_done"))
    except BotorlError:
        return False  # a damaged checkpoint is not a finished stage


def observation_spaces(cfg):
    """(the policy's flat observation space, the env's own one) of the run's task; (None, None)
    when its env cannot be made here (the contract then lists the layout without shapes)."""
    try:
        env = get_task(cfg.task).make_env(seed=0)
    except Exception:  # noqa: BLE001 - the bounds are a courtesy; an unbuildable env must not stop the export
        return None, None
    try:
        inner = env
        while not isinstance(inner, TaskEnv) and hasattr(inner, "env"):
            inner = inner.env  # TimeLimit -> the task env
        own = inner.env.observation_space if isinstance(inner, TaskEnv) else None
        return env.observation_space, own
    finally:
        with contextlib.suppress(Exception):
            env.close()


def _bounds(x) -> list[float | None]:
    """Bounds for JSON: an infinite bound is null (JSON has no infinity)."""
    return [float(v) if np.isfinite(v) else None for v in np.asarray(x, np.float64).reshape(-1)]


def observation_layout(obs_keys, own_space) -> list[dict[str, Any]] | None:
    """Each leaf of a Dict observation in flattening order: key ("a/b" nested), shape, offset and
    size in the flat vector, bounds (null where the env could not be built here)."""
    if obs_keys is None:
        return None
    out, offset = [], 0
    for key in obs_keys:
        space = own_space
        for part in key.split("/"):
            space = space.spaces[part] if space is not None else None
        shape = None if space is None else [int(s) for s in space.shape]
        size = None if shape is None else int(np.prod(shape, dtype=np.int64))
        out.append({"key": key, "shape": shape, "offset": offset, "size": size,
                    "low": None if space is None else _bounds(space.low),
                    "high": None if space is None else _bounds(space.high)})
        offset = None if (offset is None or size is None) else offset + size
    return out


def verification_observations(cfg, run, n: int, seed: int = 0, why: str | None = None) -> tuple[np.ndarray, str]:
    """``n`` observations of the run's dataset and where they came from; standard normal ones
    when the data cannot be read here (``why``: the task cannot be built here; a pickle)."""
    from botorl.pipeline.runner import load_run_data  # lazy: JAX; botorl.api imports this module

    try:
        if why is not None:
            raise BotorlError(why)
        obs = np.asarray(load_run_data(cfg, run.config).observations, np.float32)
    except BotorlError as err:
        print(f"botorl export: the run's dataset cannot be read here ({err}); verifying on {n} standard normal "
              f"observations instead (the contract's verification.source says so).", file=sys.stderr)
        obs = np.random.default_rng(seed).standard_normal((n, int(task_io(cfg)["obs_dim"])))
        return obs.astype(np.float32), "standard-normal"
    idx = np.random.default_rng(seed).choice(len(obs), size=n, replace=len(obs) < n)
    return obs[idx], "dataset"


# ------------------------------------------------------------------ the graph
def policy_function(policy):
    """``load_policy``'s deterministic chain after ``flatten_obs`` as one JAX function of (B, obs_dim)
    float32: ``eval_fn`` (what ``agent.eval_actions`` jits) then ``action_to_env`` in float32."""
    # lazy: JAX; botorl.api imports this module
    import jax.numpy as jnp

    from botorl.agents.common import acting_view, eval_fn

    view = acting_view(policy.agent)
    unit_box = is_unit_box(policy.action_low, policy.action_high)
    low = jnp.asarray(policy.action_low, jnp.float32)
    high = jnp.asarray(policy.action_high, jnp.float32)

    def act(observations):
        a = jnp.clip(eval_fn(view, observations), -1.0, 1.0)
        if unit_box:  # botorl's own tasks: action_to_env is the identity, kept exact
            return a
        return jnp.clip(low + (a + 1.0) * 0.5 * (high - low), low, high)

    return act


def convert(policy, opset: int = OPSET) -> bytes:
    """The ONNX model (serialised) of ``policy_function(policy)``, batch axis dynamic."""
    mods = require("onnx", "jax2onnx")
    model = mods["jax2onnx"].to_onnx(policy_function(policy), [("B", policy.obs_dim)], model_name="botorl_policy",
                                     opset=opset, input_names=[INPUT_NAME], output_names=[OUTPUT_NAME])
    mods["onnx"].checker.check_model(model)
    return model.SerializeToString()


# ------------------------------------------------------------------ running a model
class OnnxPolicy:
    """An exported model through onnxruntime: ``policy(obs)`` (B, obs_dim) -> (B, action_dim) in
    the env's bounds, as ``Policy`` is called on flat observations."""

    def __init__(self, path: str | Path | bytes):
        self.path = None if isinstance(path, bytes) else Path(path)
        if self.path is not None:
            path = _model_bytes(self.path)
        ort = require("onnxruntime")["onnxruntime"]
        check_graph(path, self.path or "the model")
        try:
            self.session = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
        except Exception as err:  # noqa: BLE001 - onnxruntime raises its own types for a bad file
            raise ConfigError(f"{self.path or 'the model'} cannot be loaded by onnxruntime ({err}); give a model "
                              f"`botorl export` wrote.") from None
        ins, outs = self.session.get_inputs(), self.session.get_outputs()
        if [i.name for i in ins] != [INPUT_NAME] or OUTPUT_NAME not in [o.name for o in outs]:
            raise ConfigError(f"{self.path or 'the model'} takes {[i.name for i in ins]} and gives "
                              f"{[o.name for o in outs]}; a botorl policy takes '{INPUT_NAME}' and gives "
                              f"'{OUTPUT_NAME}'.")
        def width(shape):  # of (batch, width) observations or actions; None where the model leaves it open
            return shape[-1] if len(shape) == 2 and isinstance(shape[-1], int) else None

        self.obs_dim = width(ins[0].shape)
        self.action_dim = width(next(o.shape for o in outs if o.name == OUTPUT_NAME))

    def __call__(self, observations) -> np.ndarray:
        obs = np.asarray(observations, np.float32)
        try:
            out = self.session.run([OUTPUT_NAME], {INPUT_NAME: obs.reshape(-1, obs.shape[-1])})[0]
            return np.asarray(out).reshape(*obs.shape[:-1], -1)
        except Exception as err:  # noqa: BLE001 - onnxruntime's own errors, a reshape of a wrong output
            raise ConfigError(f"{self.path or 'the model'} failed on observations of shape {obs.shape} "
                              f"({type(err).__name__}: {err}); give a model `botorl export` wrote.") from None


MAX_MODEL_BYTES = 1 << 30  # a policy of 256x256 layers is under 1 MB


def _model_bytes(path: Path) -> bytes:
    """The model file's bytes, a link followed: a regular file (a FIFO would hang) of at most ``MAX_MODEL_BYTES``."""
    try:
        return read_bounded_bytes(os.path.realpath(path), MAX_MODEL_BYTES)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such model file; give the FILE.onnx that `botorl export` wrote.") from None
    except ValueError as err:  # not a regular file, or too large for a policy model
        raise ConfigError(f"{path}: {err}; give the FILE.onnx that `botorl export` wrote.") from None
    except OSError as err:
        raise ConfigError(f"{path}: cannot be read ({err.strerror}).") from None


# A botorl policy is a straight chain of layers; a loop (whose trip count can be 2**62) or a branch
# is no policy of botorl's, and onnxruntime would run it without bound. Nor is a convolution, an
# einsum or a recurrent cell: operators whose work the bounds below do not count.
CONTROL_FLOW = ("Loop", "Scan", "If", "SequenceMap")
UNCOUNTED = ("Conv", "ConvTranspose", "ConvInteger", "QLinearConv", "DeformConv", "Einsum", "LSTM", "GRU", "RNN",
             "MatMulInteger", "QLinearMatMul")


def check_graph(model: bytes, where) -> None:
    """ConfigError when the model (bytes) holds a control-flow or uncounted operator, anywhere in
    its graph or functions, or when its work is not bounded (``graph_work``); nothing is run. The
    bounds, per observation: the MatMul/Gemm FLOPs and any one tensor of the largest actor a config
    may give (``configs.resolve.MAX_PARAMS`` weights), all node outputs together four times that."""
    from botorl.configs.resolve import MAX_PARAMS  # lazy: JAX (the configs' schema); botorl.api imports this module

    onnx = require("onnx")["onnx"]
    try:
        proto = onnx.load_from_string(model)
    except Exception as err:  # noqa: BLE001 - protobuf's decode errors
        raise ConfigError(f"{where} is not an ONNX model ({type(err).__name__}); give a model `botorl export` "
                          f"wrote.") from None
    nodes = list(proto.graph.node) + [n for f in proto.functions for n in f.node]
    bad = sorted({n.op_type for n in nodes if n.op_type in CONTROL_FLOW})
    if bad:
        raise ConfigError(f"{where} holds the control-flow operator(s) {', '.join(bad)}; a policy botorl exports is "
                          f"a plain chain of layers, and a loop could run without end. Give a model `botorl export` "
                          f"wrote.")
    odd = sorted({n.op_type for n in nodes if n.op_type in UNCOUNTED or n.domain not in ("", "ai.onnx")})
    if odd or proto.functions:
        raise ConfigError(f"{where} holds operators no botorl policy has ({', '.join(odd) or 'model-local functions'}), "
                          f"whose work botorl cannot bound. Give a model `botorl export` wrote.")
    one, two = graph_work(onnx, proto, 1, where, MAX_PARAMS), graph_work(onnx, proto, 2, where, MAX_PARAMS)
    flops, elements = one
    if two[0] > 2 * flops or two[1] > 2 * elements:  # work that grows faster than the batch
        raise ConfigError(f"{where}: its work grows faster than the number of observations ({flops:,} FLOPs for one, "
                          f"{two[0]:,} for two); a policy acts on each observation alone. Give a model `botorl export` wrote.")
    if flops > 2 * MAX_PARAMS or elements > 4 * MAX_PARAMS:
        raise ConfigError(f"{where}: its graph does {flops:,} MatMul/Gemm FLOPs and makes {elements:,} values per "
                          f"observation, more than the largest policy botorl trains ({2 * MAX_PARAMS:,} and "
                          f"{4 * MAX_PARAMS:,}); it would run for hours. Give a model `botorl export` wrote.")


def graph_work(onnx, proto, batch: int, where, max_tensor: int) -> tuple[int, int]:
    """(MatMul/Gemm FLOPs, values made by all nodes) of one call on ``batch`` observations, from
    ONNX's shape inference; ConfigError when a node's output has a shape inference cannot fix (it
    would depend on the observations' values: a ``Range`` or ``ConstantOfShape`` sized by data) or
    one tensor holds more than ``max_tensor`` values per observation."""
    model = onnx.ModelProto()
    model.CopyFrom(proto)
    inputs = [i for i in model.graph.input if i.name not in {t.name for t in model.graph.initializer}]
    for i in inputs:
        dims = i.type.tensor_type.shape.dim
        if len(dims) != 2 or not dims[1].HasField("dim_value"):
            raise ConfigError(f"{where}: input {i.name!r} is not (batch, width) with a fixed width; a botorl policy "
                              f"takes (batch, obs_dim) observations.")
        dims[0].Clear()
        dims[0].dim_value = batch
    try:
        inferred = onnx.shape_inference.infer_shapes(model, strict_mode=True, data_prop=True)
    except Exception as err:  # noqa: BLE001 - onnx's inference errors
        raise ConfigError(f"{where}: its graph's shapes cannot be inferred ({type(err).__name__}: {str(err)[:200]}); "
                          f"give a model `botorl export` wrote.") from None
    g = inferred.graph
    shapes = {t.name: list(t.dims) for t in g.initializer}
    for v in [*g.input, *g.value_info, *g.output]:
        dims = v.type.tensor_type.shape.dim
        shapes[v.name] = [d.dim_value if d.HasField("dim_value") else None for d in dims] \
            if v.type.tensor_type.HasField("shape") else None
    flops = elements = 0
    for node in g.node:
        for out in filter(None, node.output):
            dims = shapes.get(out)
            if dims is None or None in dims:
                raise ConfigError(f"{where}: node {node.name or node.op_type} ({node.op_type}) makes {out!r} of a shape "
                                  f"that depends on the observations' values, so its size has no bound; give a model "
                                  f"`botorl export` wrote.")
            size = int(np.prod(dims, dtype=object))
            if size > max_tensor * batch:
                raise ConfigError(f"{where}: node {node.name or node.op_type} ({node.op_type}) makes {size:,} values "
                                  f"for {batch} observation(s), more than {max_tensor:,} each; give a model "
                                  f"`botorl export` wrote.")
            elements += size
        if node.op_type in ("MatMul", "Gemm"):
            a, out = shapes.get(node.input[0]) or [1], shapes[node.output[0]]
            trans_a = any(at.name == "transA" and at.i for at in node.attribute)
            k = a[0] if (trans_a or len(a) == 1) else a[-1]
            flops += 2 * int(np.prod(out, dtype=object)) * int(k or 1)
    return flops, elements


def max_gap(a, b) -> tuple[float, int]:
    """The max abs difference of two action batches and the row where it is."""
    d = np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))
    if not np.all(np.isfinite(d)):
        return float("inf"), int(np.argwhere(~np.isfinite(d))[0][0])
    return float(d.max()), int(np.unravel_index(int(d.argmax()), d.shape)[0])


# ------------------------------------------------------------------ the whole export
def observation_entry(cfg, policy, here: str | None) -> dict[str, Any]:
    """The contract's ``observation``: size, bounds and a Dict's layout (``here``: why the task
    cannot be built here, None when it can)."""
    flat_space, own_space = observation_spaces(cfg) if here is None else (None, None)
    layout = observation_layout(policy.obs_keys, own_space)
    if layout is not None and own_space is not None:  # a Dict: its leaves' bounds in the flat order
        low, high = [v for leaf in layout for v in leaf["low"]], [v for leaf in layout for v in leaf["high"]]
    else:  # a Box env of one's own has its own bounds; botorl's task envs are unbounded
        space = own_space if getattr(own_space, "shape", None) == (policy.obs_dim,) else flat_space
        low, high = (None, None) if space is None else (_bounds(space.low), _bounds(space.high))
    return {"dim": policy.obs_dim, "low": low, "high": high, "layout": layout, "normalization": None}


def verified_gap(policy, model: bytes, obs: np.ndarray, source: str, tolerance: float, ort_version: str) -> float:
    """max |onnxruntime - load_policy| on ``obs``; ExportMismatch (nothing written) above ``tolerance``."""
    expected = policy(obs)
    gap, row = max_gap(OnnxPolicy(model)(obs), expected)
    single, _ = max_gap(OnnxPolicy(model)(obs[:1]), expected[:1])  # the batch axis is dynamic: B = 1 too
    gap = max(gap, single)
    if not gap <= tolerance:
        raise ExportMismatch(f"the exported model does not act as load_policy: max |onnxruntime - load_policy| = "
                             f"{gap:.3g} (row {row} of {len(obs)} {source} observations) > {tolerance:g}; nothing "
                             f"was written. Report it with the run's config.json and the versions of jax2onnx "
                             f"({package_version('jax2onnx')}) and onnxruntime ({ort_version}).")
    return gap


def export_policy(run_dir, path, checkpoint: str | None = None, format: str = "onnx", force: bool = False,
                  observations=None, verify_rows: int = VERIFY_ROWS, tolerance: float = TOLERANCE,
                  opset: int = OPSET, env: str | None = None) -> dict[str, Any]:
    """Write ``path`` (the ONNX model) and ``path.json`` (its contract) for a run's policy and
    return the contract. ``observations``: the (N, obs_dim) batch to verify on (default:
    ``verify_rows`` of the run's dataset). ``ExportMismatch`` (exit 1, nothing written) when
    onnxruntime's actions differ from ``load_policy``'s by more than ``tolerance``; needs
    ``pip install "botorl[export]"``. ``env``: a task of one's own's entry point, given again by
    the user (``--env``; without it the verification uses standard normal observations)."""
    if format not in FORMATS:
        raise ConfigError(f"--format {format}: botorl exports {', '.join(FORMATS)}.")
    out = Path(path)
    meta = contract_path(out)
    for p in (out, meta):
        check_replaceable(p, force)
    check_writable_folder(out)
    run, cfg = read_run(run_dir, "export")
    check_exportable(run, checkpoint)
    _, name, state = check_checkpoint(run, cfg, checkpoint)  # what `botorl eval` refuses, export refuses too
    mods = require("onnx", "onnxruntime", "jax2onnx")  # before any JAX work: a missing extra costs nothing
    setup_jax()

    register_given(cfg, env)
    if cfg.env.entry is not None and env is None:
        ensure_task(cfg)  # an entry point the run recorded: the user gives it again (--env) or registers it
    try:  # the task gives the verification its dataset and the contract the env's shapes
        ensure_task(cfg)
        here = None
    except BotorlError as err:  # a task registered from a script: standard normal observations
        here = str(err)
    policy = load_policy(run.root, checkpoint=name, deterministic=True)

    if observations is None:
        obs, source = verification_observations(cfg, run, verify_rows, seed=cfg.seed, why=here)
    else:
        obs, source = np.asarray(observations, np.float32), "given"
        if obs.ndim != 2 or obs.shape[1] != policy.obs_dim or len(obs) == 0:
            raise ConfigError(f"observations of shape {obs.shape}: give (N, {policy.obs_dim}) flat observations.")
    model = convert(policy, opset=opset)
    gap = verified_gap(policy, model, obs, source, tolerance, mods["onnxruntime"].__version__)
    contract = {
        "format": "onnx",
        "model": out.name,
        "sha256": hashlib.sha256(model).hexdigest(),
        "opset": int(opset),
        "input": {"name": INPUT_NAME, "shape": ["batch", policy.obs_dim], "dtype": "float32"},
        "output": {"name": OUTPUT_NAME, "shape": ["batch", policy.action_dim], "dtype": "float32"},
        "observation": observation_entry(cfg, policy, here),
        "action": {"dim": policy.action_dim, "low": _bounds(policy.action_low), "high": _bounds(policy.action_high),
                   "deterministic": True},
        "task": cfg.task,
        "method": cfg.method,
        "seed": int(cfg.seed),
        "alpha": None if cfg.alpha is None else float(cfg.alpha),
        "checkpoint": name,
        "stage": state.get("stage"),
        "step": checkpoint_step(cfg, state),
        "botorl_version": botorl_version,
        "converter": {"name": "jax2onnx", "version": package_version("jax2onnx")},
        "verification": {"runtime": f"onnxruntime {mods['onnxruntime'].__version__}", "observations": len(obs),
                         "source": source, "max_abs_gap": gap, "tolerance": tolerance},
    }
    for p in (out, meta):  # again: the minutes of conversion are time for a swap
        check_replaceable(p, force)
    atomic_write_bytes(out, model)
    if file_sha256(out, MAX_MODEL_BYTES) != contract["sha256"]:  # what is on disk is what was verified
        raise BotorlError(f"{out} does not read back as written (sha256 differs); check the disk and export again.")
    atomic_write_json(meta, contract)
    return contract


def read_contract(model: str | Path) -> dict[str, Any] | None:
    """The contract beside a model (None when there is none); ConfigError if it is unreadable."""
    p = contract_path(model)
    if not p.exists():
        return None
    try:
        c = read_json(p)
    except (OSError, ValueError) as err:
        raise ConfigError(f"{p} cannot be read as a policy contract ({err}); export the policy again.") from None
    if not isinstance(c, dict):
        raise ConfigError(f"{p} is not a policy contract (a JSON object); export the policy again.")
    return c


# ------------------------------------------------------------------ the round trip
def check_against_run(model: OnnxPolicy, contract: dict | None, cfg, path: Path) -> None:
    """ConfigError unless the model is this run's policy as exported: the contract's task, shapes,
    action bounds and sha256 agree with the run and with the model (checked before it runs)."""
    io = task_io(cfg)
    if contract is None:
        print(f"botorl eval: {contract_path(path)} is missing; checking the model's shapes only.", file=sys.stderr)
    else:
        if contract.get("task") != cfg.task:
            raise ConfigError(f"{path} is a policy of task {contract.get('task')!r} (its contract says), not of this "
                              f"run's {cfg.task!r}; give the run it was exported from.")
        want = contract.get("sha256")
        if not isinstance(want, str) or hashlib.sha256(_model_bytes(path)).hexdigest() != want:
            raise ConfigError(f"{path} is not the file its contract describes (sha256 differs): it changed since "
                              f"`botorl export`; export it again.")

        def said(part, key):
            node = contract.get(part)
            return node.get(key) if isinstance(node, dict) else None

        wrong = [f"{what} {got!r} in the contract, {want_!r} for the run" for what, got, want_ in (
            ("input width", said("input", "shape"), ["batch", io["obs_dim"]]),
            ("output width", said("output", "shape"), ["batch", io["action_dim"]]),
            ("action low", said("action", "low"), _bounds(io["action_low"])),
            ("action high", said("action", "high"), _bounds(io["action_high"]))) if got != want_]
        if wrong:
            raise ConfigError(f"{contract_path(path)} does not describe this run's policy ({'; '.join(wrong)}); export "
                              f"the policy again.")
    for verb, got, want, what in (("takes", model.obs_dim, io["obs_dim"], "observation"),
                                  ("gives", model.action_dim, io["action_dim"], "action")):
        if got is not None and got != want:
            raise ConfigError(f"{path} {verb} {got} {what} values; this run's task {cfg.task!r} has {want}.")


def evaluate_exported(run, cfg, path, episodes: int | None = None) -> dict[str, Any]:
    """``botorl eval RUN --policy FILE``: ``botorl eval``'s episodes with the exported model
    acting through onnxruntime; written to ``RUN/eval-<FILE stem>-onnx.json``."""
    from botorl.pipeline.evaluation import evaluate_command  # lazy: JAX; botorl.api imports this module

    path = Path(path)
    model = OnnxPolicy(path)  # exit 2 when onnxruntime is missing or the file is not a model
    contract = read_contract(path)
    check_against_run(model, contract, cfg, path)
    io = task_io(cfg)
    unit_box = is_unit_box(io["action_low"], io["action_high"])
    n = cfg.eval.episodes if episodes is None else int(episodes)

    def act(obs):  # (1, E, O) -> (1, E, A): the task env takes [-1, 1] and maps it onto the env's box itself
        a = model(obs[0])
        if a.shape != (obs.shape[1], io["action_dim"]) or not np.all(np.isfinite(a)):
            raise ConfigError(f"{path} gave actions of shape {a.shape}{'' if np.all(np.isfinite(a)) else ' with NaN/inf'} "
                              f"for {obs.shape[1]} observations; this run's task takes ({obs.shape[1]}, "
                              f"{io['action_dim']}) finite actions. Export the policy again.")
        return (a if unit_box else action_from_env(a, io["action_low"], io["action_high"]).astype(np.float32))[None]

    head = {"policy": str(path), **{k: (contract or {}).get(k) for k in ("checkpoint", "stage", "step")}}
    return evaluate_command(act, cfg, n, head, run.root / f"eval-{path.stem}-onnx.json")

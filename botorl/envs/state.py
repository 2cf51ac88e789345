"""The full state of a botorl env mid-episode, as plain JSON, for an exact resume (CONTRACTS.md,
"Tasks"): per MuJoCo model ``mj_getState(mjSTATE_INTEGRATION)`` (everything ``mj_step`` reads)
plus the model fields the envs move at reset; every wrapper layer's plain attributes (numbers,
strings, arrays and containers of them; objects such as models are not state); every layer's
``np_random`` and its action space's generator. Floats round-trip exactly through JSON, so a
restored env steps bit-identically (tests/test_envs_state.py).
"""

from __future__ import annotations

import contextlib
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np

FORMAT = "botorl-env-state-v1"
_INTEGRATION = mujoco.mjtState.mjSTATE_INTEGRATION  # everything mj_step reads
_MODEL_FIELDS = ("body_pos", "body_quat", "site_pos", "site_quat")
# Attributes that are configuration of this process, not of the episode.
_SKIP = {"render_mode", "tmp_xml_file_path", "fullpath", "camera_name", "camera_id", "width", "height",
         "_np_random", "np_random"}


class _Skip(Exception):
    pass


def _encode(v: Any, depth: int = 0) -> Any:
    if depth > 6:
        raise _Skip
    if v is None or isinstance(v, (bool, str)):
        return v
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v)
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, np.ndarray):
        if v.dtype == object or v.dtype.kind not in "biuf":
            raise _Skip
        return {"__ndarray__": v.ravel().tolist(), "dtype": v.dtype.str, "shape": list(v.shape)}
    if type(v) in (list, tuple):
        return {f"__{type(v).__name__}__": [_encode(x, depth + 1) for x in v]}
    if isinstance(v, (set, frozenset)):
        return {"__set__": sorted((_encode(x, depth + 1) for x in v), key=repr), "frozen": isinstance(v, frozenset)}
    if isinstance(v, dict):
        if not all(isinstance(k, str) for k in v):
            raise _Skip
        return {"__dict__": {k: _encode(x, depth + 1) for k, x in v.items()}}
    raise _Skip


def _decode(v: Any) -> Any:
    if not isinstance(v, dict):
        return v
    if "__ndarray__" in v:
        return np.asarray(v["__ndarray__"], dtype=np.dtype(v["dtype"])).reshape(v["shape"])
    if "__list__" in v:
        return [_decode(x) for x in v["__list__"]]
    if "__tuple__" in v:
        return tuple(_decode(x) for x in v["__tuple__"])
    if "__set__" in v:
        return (frozenset if v.get("frozen") else set)(_decode(x) for x in v["__set__"])
    if "__dict__" in v:
        return {k: _decode(x) for k, x in v["__dict__"].items()}
    raise ValueError(f"not an encoded env-state value: {sorted(v)}")


def _layers(env: gym.Env) -> list[tuple[str, Any]]:
    """(path, object) of every part that holds state: wrappers outside-in, the env, its sub-envs."""
    out = []
    e, i = env, 0
    while isinstance(e, gym.Wrapper):
        out.append((f"wrapper{i}", e))
        e, i = e.env, i + 1
    out.append(("env", e))
    out += [(f"env.{name}", val) for name, val in sorted(vars(e).items()) if isinstance(val, gym.Env) and val is not e]
    return out


def _encode_rng(rng) -> dict | None:
    if not isinstance(rng, np.random.Generator):
        return None
    st = rng.bit_generator.state
    return {"bit_generator": st["bit_generator"], "state": _encode(st)}


# The bit generators a state may name: a fixed table, as the name comes from a file (envs.json) and
# NumPy's namespace holds functions too (np.random.test would run NumPy's test suite).
BIT_GENERATORS = {bg.__name__: bg for bg in (np.random.PCG64, np.random.PCG64DXSM, np.random.Philox,
                                             np.random.SFC64, np.random.MT19937)}


def _decode_rng(d: dict) -> np.random.Generator:
    name = d["bit_generator"]
    if not isinstance(name, str) or name not in BIT_GENERATORS:
        raise ValueError(f"bit generator {name!r} is none of {', '.join(BIT_GENERATORS)}")
    bg = BIT_GENERATORS[name]()
    bg.state = _decode(d["state"])
    return np.random.Generator(bg)


def _mujoco(obj):
    """(model, data) if ``obj`` holds a MuJoCo simulation of its own, else None."""
    model, data = obj.__dict__.get("model"), obj.__dict__.get("data")
    return (model, data) if isinstance(model, mujoco.MjModel) and isinstance(data, mujoco.MjData) else None


def get_env_state(env: gym.Env) -> dict[str, Any]:
    """Everything that decides the env's future, as a JSON-serialisable dict."""
    layers, sims, seen = {}, {}, set()
    for path, obj in _layers(env):
        attrs = {}
        for name, val in vars(obj).items():
            if name in _SKIP or name == "env" or isinstance(val, gym.Env):
                continue
            with contextlib.suppress(_Skip):
                attrs[name] = _encode(val)
        space_rng = getattr(getattr(obj, "action_space", None), "_np_random", None)
        layers[path] = {"class": type(obj).__name__, "attrs": attrs,
                        "np_random": _encode_rng(getattr(obj, "_np_random", None)),
                        "action_space_rng": _encode_rng(space_rng)}
        sim = _mujoco(obj)
        if sim is not None and id(sim[1]) not in seen:
            seen.add(id(sim[1]))
            model, data = sim
            buf = np.empty(mujoco.mj_stateSize(model, _INTEGRATION), np.float64)
            mujoco.mj_getState(model, data, buf, _INTEGRATION)
            sims[path] = {"integration": _encode(buf),
                          **{f: _encode(np.array(getattr(model, f))) for f in _MODEL_FIELDS}}
    return {"format": FORMAT, "layers": layers, "mujoco": sims}


def _ints(v: Any):
    """Every integer in a decoded attribute value (inside containers and integer arrays)."""
    if isinstance(v, np.ndarray):
        if v.dtype.kind in "iu" and v.size:
            yield int(np.abs(v.astype(object)).max())
    elif isinstance(v, (list, tuple, set, frozenset, dict)):
        for x in v.values() if isinstance(v, dict) else v:
            yield from _ints(x)
    elif isinstance(v, int) and not isinstance(v, bool):
        yield abs(v)


def _count_bound(env: gym.Env, steps: int) -> int | None:
    """The largest integer a restored attribute may take: no counter passes the fresh env's episode
    horizon or, counted over episodes, the ``steps`` the env has taken (None: no horizon known)."""
    e = env
    while isinstance(e, gym.Wrapper):
        if isinstance(e, gym.wrappers.TimeLimit):
            return max(int(e._max_episode_steps), steps)
        e = e.env
    return None


def _check_counts(path: str, name: str, val: Any, cur: Any, bound: int | None) -> None:
    """ValueError when the restored ``val`` of attribute ``name`` changes the fresh env's ``cur``
    and holds an integer beyond ``bound``: a count such as ``frame_skip = 10**9`` would make one
    env step run for hours, where no signal stops it. A seed is no count."""
    if bound is None or "seed" in name or (type(val) is type(cur) and _same(val, cur)):
        return
    big = max(_ints(val), default=0)
    if big > bound:
        raise ValueError(f"env state: {path}.{name} holds {big:,}, more than the {bound:,} steps of an episode or "
                         f"of the run so far; it is no state of this task's env")


def _same(a: Any, b: Any) -> bool:
    try:
        return bool(np.array_equal(a, b)) if isinstance(a, np.ndarray) else bool(a == b)
    except Exception:  # noqa: BLE001 - values whose == is not a truth value
        return False


def set_env_state(env: gym.Env, state: dict[str, Any], steps: int = 0) -> None:
    """Restore ``get_env_state``'s dict into ``env`` (built the same way: same task and wrappers).
    ``steps``: the env steps taken before the state was saved; a restored integer that changes an
    attribute may exceed neither them nor the env's episode horizon (``_check_counts``)."""
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise ValueError(f"not an env state of format {FORMAT!r}")
    bound = _count_bound(env, steps)
    layers = dict(_layers(env))
    if set(layers) != set(state["layers"]):
        raise ValueError(f"env state of layers {sorted(state['layers'])} does not fit this env ({sorted(layers)})")
    for path, saved in state["layers"].items():
        obj = layers[path]
        if type(obj).__name__ != saved["class"]:
            raise ValueError(f"env state: {path} is a {type(obj).__name__} here, a {saved['class']} in the state")
        for name, enc in saved["attrs"].items():
            # plain attributes only: a name the file gives must not shadow a method (env.step) or a dunder
            if not isinstance(name, str) or name.startswith("__") or callable(getattr(type(obj), name, None)):
                raise ValueError(f"env state: {path} names attribute {name!r}, which is no plain attribute")
            val = _decode(enc)
            cur = obj.__dict__.get(name)
            _check_counts(path, name, val, cur, bound)
            if isinstance(cur, np.ndarray) and isinstance(val, np.ndarray) and cur.shape == val.shape \
                    and cur.dtype == val.dtype and cur.flags.writeable:
                cur[...] = val  # in place: other objects may hold a view of it
            else:
                obj.__dict__[name] = val
        if saved["np_random"] is not None:
            obj._np_random = _decode_rng(saved["np_random"])
        if saved["action_space_rng"] is not None:
            obj.action_space._np_random = _decode_rng(saved["action_space_rng"])
    for path, sim_state in state["mujoco"].items():
        sim = _mujoco(layers[path])
        if sim is None:
            raise ValueError(f"env state: {path} has no MuJoCo simulation here")
        model, data = sim
        for f in _MODEL_FIELDS:
            getattr(model, f)[...] = _decode(sim_state[f])
        buf = _decode(sim_state["integration"])
        if buf.size != mujoco.mj_stateSize(model, _INTEGRATION):
            raise ValueError(f"env state: {path}'s MuJoCo state has {buf.size} numbers, this model needs "
                             f"{mujoco.mj_stateSize(model, _INTEGRATION)}")
        mujoco.mj_setState(model, data, buf, _INTEGRATION)
        # derived quantities (positions, sensors) for code that reads them before the next step
        mujoco.mj_forward(model, data)

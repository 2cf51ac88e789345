"""Issue 51: nothing from a user's folders runs as code, and a sweep touches only its own.

- Pickles: every pickle botorl reads (Cal-QL's ``.npy`` object arrays, DAPG's demos) goes through
  one restricted unpickler (``data.safe.read_plain_pickle``): plain data and NumPy arrays only; a
  crafted ``__reduce__`` is refused (exit 2) and never called, which a marker file shows.
- Env states: the bit generator envs.json names comes from a fixed table, never from NumPy's
  namespace (``np.random.test`` ran NumPy's test suite).
- Sweeps: a trial imports nothing from the sweep folder or its own folder (a planted numpy.py,
  json.py, ...), and a sweep signals or deletes only processes and temp folders it can prove are
  its own: a token bound to the sweep folder's identity, a temp folder's inode and a mark inside it.

Each test fails on the code before issue 51 (the marker appeared, the bystander died, the outside
folder was deleted) and runs in seconds (stand-in trial commands, no training).
"""

from __future__ import annotations

import builtins
import collections
import json
import os
import pickle
import signal
import socket
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import subprocess_env
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from botorl.cli import main as botorl_main
from botorl.data.safe import read_plain_pickle
from botorl.errors import DataFormatError

EXAMPLES = int(os.environ.get("BOTORL_HYPOTHESIS_EXAMPLES", "25"))


class _Payload:
    """Unpickling this creates ``marker`` (a stand-in for any shell command)."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (builtins.open, (self.marker, "w"))


def _object_npy(path: Path, items: list) -> Path:
    arr = np.empty(len(items), dtype=object)
    for i, item in enumerate(items):  # one by one: a list item stays one element
        arr[i] = item
    np.save(path, arr, allow_pickle=True)
    return path


# ----------------------------------------------------------------------------- pickles
def test_a_crafted_npy_runs_nothing_and_data_info_exits_2(tmp_path, capsys):
    marker = tmp_path / "pwned"
    evil = _object_npy(tmp_path / "door2_sparse.npy", [_Payload(marker)])
    assert botorl_main(["data", "info", str(evil)]) == 2
    err = capsys.readouterr().err
    assert "names io.open" in err and "Traceback" not in err and str(evil) in err, err
    assert not marker.exists()
    evil_pickle = tmp_path / "door-v0_demos.pickle"
    evil_pickle.write_bytes(pickle.dumps([{"observations": _Payload(marker)}]))
    assert botorl_main(["data", "info", str(evil_pickle)]) == 2
    assert "names io.open" in capsys.readouterr().err and not marker.exists()
    np.load(evil, allow_pickle=True)  # control: NumPy's own loader runs it, so the checks above can fail
    assert marker.exists()


def test_calql_files_as_numpy_1_and_2_and_any_protocol_write_them_still_load(tmp_path):
    """Cal-QL's files are pickled object arrays of dicts written by NumPy 1 (``numpy.core``,
    protocol 3); NumPy 2 writes ``numpy._core``; protocol 2 spells bytes with ``_codecs.encode``."""
    from test_data_loaders import calql_files

    from botorl.data.loaders import load_calql_adroit

    expert, bc = calql_files(tmp_path)
    want = load_calql_adroit(expert, bc)
    trajs = list(np.load(expert, allow_pickle=True))
    header = expert.read_bytes()[:expert.read_bytes().index(b"\n") + 1]
    for protocol in (2, 3, 4, 5):
        raw = pickle.dumps(np.asarray(trajs + [None])[:-1], protocol=protocol)
        for spelling in (b"numpy._core", b"numpy.core"):
            if protocol <= 3:  # text GLOBAL opcodes: the module's name can be respelled in place
                raw = raw.replace(b"numpy._core", spelling)
            (tmp_path / "x.npy").write_bytes(header + raw)
            got = load_calql_adroit(tmp_path / "x.npy", bc)
            np.testing.assert_array_equal(got.observations, want.observations)
            np.testing.assert_array_equal(got.rewards, want.rewards)
    plain = {"a": [1, 2.5, True, None, "s", b"b", (3, 4)], "o": collections.OrderedDict(x=np.float32(1)),
             "arr": np.arange(6).reshape(2, 3)[:, ::2]}
    (tmp_path / "p.pickle").write_bytes(pickle.dumps([plain], protocol=2))
    got = read_plain_pickle(tmp_path / "p.pickle", "pickle")[0]
    assert got["a"] == plain["a"] and got["o"] == plain["o"] and got["arr"].tolist() == [[0, 2], [3, 5]]


_leaf = st.one_of(st.none(), st.booleans(), st.integers(), st.floats(allow_nan=False), st.text(max_size=8),
                  st.binary(max_size=8),
                  hnp.arrays(st.sampled_from([np.float32, np.float64, np.int64, np.bool_]), hnp.array_shapes(max_dims=2,
                             max_side=4)),
                  st.just("PAYLOAD"))
_tree = st.recursive(_leaf, lambda kids: st.one_of(st.lists(kids, max_size=4), st.tuples(kids, kids),
                                                   st.dictionaries(st.text(max_size=4), kids, max_size=4)),
                     max_leaves=12)


@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck))
@given(tree=_tree, protocol=st.integers(2, 5), as_npy=st.booleans(),
       callable_=st.sampled_from([builtins.open, os.system, np.random.seed, collections.Counter, exec]))
def test_any_pickle_gives_its_plain_data_or_exit_2_and_runs_nothing(tree, protocol, as_npy, callable_):
    """A crafted pickle: any tree of containers, numbers, strings and arrays in which a payload
    (a callable named with arguments, as ``__reduce__`` makes it) may sit anywhere."""

    with tempfile.TemporaryDirectory() as d:
        marker = Path(d) / "pwned"

        class Payload:
            def __reduce__(self):
                return (callable_, (str(marker), "w") if callable_ is builtins.open else (str(marker),))

        def planted(x):
            if isinstance(x, str) and x == "PAYLOAD":
                return Payload()
            if isinstance(x, list):
                return [planted(v) for v in x]
            if isinstance(x, tuple):
                return tuple(planted(v) for v in x)
            if isinstance(x, dict):
                return {k: planted(v) for k, v in x.items()}
            return x

        path = Path(d) / ("f.npy" if as_npy else "f.pickle")
        if as_npy:
            _object_npy(path, [planted(tree)])
        else:
            path.write_bytes(pickle.dumps(planted(tree), protocol=protocol))
        has_payload = "PAYLOAD" in repr(tree)
        try:
            got = read_plain_pickle(path, "data file")
        except DataFormatError as err:
            assert has_payload and " names " in str(err)
        else:
            assert not has_payload
            got = got[0] if as_npy else got
            assert pickle.dumps(got, protocol=5) == pickle.dumps(tree, protocol=5)
        assert not marker.exists()


# ----------------------------------------------------------------------------- env states
def test_an_env_state_naming_a_numpy_function_calls_nothing(tmp_path, monkeypatch):
    from botorl.envs.registry import get_task
    from botorl.envs.state import get_env_state, set_env_state

    marker = tmp_path / "pwned"
    # a function in NumPy's namespace, as np.random.test is (which runs NumPy's test suite)
    monkeypatch.setattr(np.random, "planted", lambda *a: marker.write_text("ran"), raising=False)
    env = get_task("pointmaze-umaze").make_env(seed=0)
    env.reset()
    good = json.loads(json.dumps(get_env_state(env)))
    set_env_state(env, good)  # control: botorl's own state is restored
    for name in ("planted", "test", "default_rng", 7, None):
        bad = json.loads(json.dumps(good))
        bad["layers"]["env"]["np_random"]["bit_generator"] = name
        with pytest.raises(ValueError, match="bit generator"):
            set_env_state(env, bad)
    env.close()
    assert not marker.exists()

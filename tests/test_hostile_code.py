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
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import Payload, subprocess_env
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from botorl.cli import main as botorl_main
from botorl.data.safe import read_plain_pickle
from botorl.errors import DataFormatError

EXAMPLES = int(os.environ.get("BOTORL_HYPOTHESIS_EXAMPLES", "25"))


def _object_npy(path: Path, items: list) -> Path:
    arr = np.empty(len(items), dtype=object)
    for i, item in enumerate(items):  # one by one: a list item stays one element
        arr[i] = item
    np.save(path, arr, allow_pickle=True)
    return path


# ----------------------------------------------------------------------------- pickles
def test_a_crafted_npy_runs_nothing_and_data_info_exits_2(tmp_path, capsys):
    marker = tmp_path / "pwned"
    evil = _object_npy(tmp_path / "door2_sparse.npy", [Payload(marker)])
    assert botorl_main(["data", "info", str(evil)]) == 2
    err = capsys.readouterr().err
    assert "names io.open" in err and "Traceback" not in err and str(evil) in err, err
    assert not marker.exists()
    evil_pickle = tmp_path / "door-v0_demos.pickle"
    evil_pickle.write_bytes(pickle.dumps([{"observations": Payload(marker)}]))
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

        class _Payload:
            def __reduce__(self):
                return (callable_, (str(marker), "w") if callable_ is builtins.open else (str(marker),))

        def planted(x):
            if isinstance(x, str) and x == "PAYLOAD":
                return _Payload()
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
    for name in ("step", "reset", "__class__", "__dict__"):  # a file's data never shadows a method
        bad = json.loads(json.dumps(good))
        bad["layers"]["env"]["attrs"][name] = 1
        with pytest.raises(ValueError, match="no plain attribute"):
            set_env_state(env, bad)
    assert callable(env.unwrapped.step)
    env.close()
    assert not marker.exists()


# ----------------------------------------------------------------------------- sweeps: no planted module
PLANTED = ("json", "ctypes", "numpy", "jax", "tyro", "contextlib")  # what the trial or its launcher imports


def _plant_modules(folder: Path, marker: Path) -> None:
    for name in PLANTED:
        (folder / f"{name}.py").write_text(f"open({str(marker)!r}, 'a').write({name!r} + ' ran in ' + __file__)\n")


def test_modules_planted_in_a_sweep_folder_never_run(tmp_path, monkeypatch):
    """The sweep folder (also the current folder) and the trial's folder hold json.py, numpy.py, ...;
    PYTHONPATH has an empty and a relative entry (both name the working directory): a trial run as
    ``python -m`` imports none of them."""
    from test_experiments_sweep_logic import FAKE

    from botorl.experiments.grid import build_grid
    from botorl.experiments.sweep import Sweep, SweepOptions

    marker = tmp_path / "pwned"
    mods = tmp_path / "mods"
    mods.mkdir()
    (mods / "fake_botorl.py").write_text(FAKE)
    out = tmp_path / "sw"
    run_dir = out / "t1" / "wsrl" / "seed0"
    run_dir.mkdir(parents=True)
    for folder in (out, run_dir):
        _plant_modules(folder, marker)
    monkeypatch.chdir(out)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(["", ".", "t1/wsrl/seed0", str(mods),
                                                      subprocess_env()["PYTHONPATH"]]))
    monkeypatch.delenv("PYTHONSAFEPATH", raising=False)
    cmd = [sys.executable, "-m", "fake_botorl"]
    grid = build_grid(tasks="t1", methods="wsrl", seeds="0")
    Sweep(grid, SweepOptions(out=out, backend="local", workers=1, command=cmd, progress=False)).run()
    assert not marker.exists(), marker.read_text()
    assert json.loads((run_dir / "summary.json").read_text())["status"] == "finished"
    # control: the same command started as before issue 51 (in the sweep folder, its path as given) imports them
    subprocess.run(cmd + ["resume", str(run_dir)], cwd=out, capture_output=True, timeout=60)
    assert " ran in " + str(out) in marker.read_text()


@pytest.mark.parametrize("case", ["planted entry point", "population member ../../outside"])
def test_a_sweep_whose_trial_refuses_its_directory_exits_2_and_runs_nothing(tmp_path, capsys, case):
    """An unfinished trial whose config.json names an entry point planted beside it (and numpy.py,
    jax.py, tyro.py in the sweep and trial folders), or a population.json naming a member outside:
    the trial's `botorl resume` refuses (exit 2), and so does the sweep, with the reason."""
    from test_rundir_hostile import _crafted_population, _edit
    from test_rundir_no_code import _plant_run

    from botorl.experiments.cli import sweep_main
    from botorl.experiments.grid import build_grid, group_populations

    marker = tmp_path / "pwned"
    out = tmp_path / "sw"
    args = ["--tasks", "pointmaze-umaze", "--methods", "wsrl", "--profile", "smoke", "--out", str(out),
            "--backend", "sequential", "--no-progress"]
    if case == "planted entry point":
        args += ["--seeds", "0"]
        trial_dir = _plant_run(out / "pointmaze-umaze" / "wsrl" / "seed0", "evilmod:make_env", marker)
        words = "--env evilmod:make_env"
    else:
        args += ["--seeds", "0,1", "--population-size", "2"]
        grid = build_grid(tasks="pointmaze-umaze", methods="wsrl", seeds="0,1", profile="smoke")
        trial_dir = _crafted_population(out / group_populations(grid.trials(), 2)[0].relpath)
        _edit(trial_dir / "population.json", lambda d: d["members"][1].update(name="../../outside"))
        words = "'../../outside', which is not a member name botorl makes"
    for folder in (out, trial_dir):
        _plant_modules(folder, marker)
    before = sorted(p.name for p in tmp_path.iterdir())
    t0 = time.monotonic()
    assert sweep_main(args) == 2
    err = capsys.readouterr().err
    assert words in err and "FAILED" in err and "Traceback" not in err, err
    assert time.monotonic() - t0 < 60 and not marker.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing made outside the sweep folder


# ----------------------------------------------------------------------------- sweeps: only their own
SLEEPER = [sys.executable, "-c", "import time; time.sleep(120)"]


@pytest.fixture()
def fake_command(tmp_path) -> list[str]:
    from test_experiments_sweep_logic import FAKE

    path = tmp_path / "fake_botorl.py"
    path.write_text(FAKE)
    return [sys.executable, str(path)]


def _stop(*procs) -> None:
    for p in procs:
        if p.poll() is None:
            p.kill()
            p.wait()


def test_a_copied_sweep_signals_and_deletes_nothing_of_the_original(tmp_path, fake_command):
    """Sweep folder A is copied to B while A's trial and Ray daemon run (both carry A's token, as a
    sweep of A started them) and A's Ray temp dir exists: a sweep of B reads A's pid file and
    sweep.json, with the right pids, start times, tokens and paths (the bystander's command line even
    holds B's trial path), and stops or deletes none of them; a sweep of A itself does (the control)."""
    import shutil

    from botorl.experiments.backend_local import TOKEN_ENV, TRIAL_PID, process_record, sweep_token
    from botorl.experiments.backend_ray import make_ray_temp_dir
    from botorl.experiments.grid import build_grid
    from botorl.experiments.sweep import Sweep, SweepOptions

    a, b = tmp_path / "A", tmp_path / "B"
    rel = Path("t1") / "wsrl" / "seed0"
    (a / rel).mkdir(parents=True)
    env = {**os.environ, TOKEN_ENV: sweep_token(a)}
    trial = subprocess.Popen(SLEEPER + [str((a / rel).resolve()), str((b / rel).resolve())], env=env)
    daemon = subprocess.Popen(SLEEPER, env=env)
    ray_dir = make_ray_temp_dir(a)
    try:
        (a / rel / TRIAL_PID).write_text(json.dumps({**process_record(trial.pid, sweep_token(a)),
                                                     "host": socket.gethostname()}))
        (a / "sweep.json").write_text(json.dumps({"ray_local_temp_dir": ray_dir,
                                                  "ray_local_processes": [process_record(daemon.pid, sweep_token(a))]}))
        shutil.copytree(a, b)
        grid = build_grid(tasks="t1", methods="wsrl", seeds="0")
        Sweep(grid, SweepOptions(out=b, backend="sequential", command=fake_command, progress=False)).run()
        assert json.loads((b / rel / "summary.json").read_text())["status"] == "finished"
        assert trial.poll() is None and daemon.poll() is None and Path(ray_dir["path"]).is_dir()
        # control: the sweep of A, whose token and temp dir these are, stops and removes them
        Sweep(grid, SweepOptions(out=a, backend="sequential", command=fake_command, progress=False)).run()
        assert trial.wait(timeout=30) != 0 and daemon.wait(timeout=30) != 0
        assert not Path(ray_dir["path"]).exists()
    finally:
        _stop(trial, daemon)
        shutil.rmtree(ray_dir["path"], ignore_errors=True)


def test_a_pid_file_or_sweep_json_naming_a_bystander_or_another_temp_dir_changes_nothing(tmp_path, fake_command):
    """A trial's pid file naming a live bystander (its command line holds the trial's path) with a
    token of the right form but not this folder's, or none; sweep.json's ray_local_temp_dir naming
    another sweep's /tmp/botorl-ray-* folder (by path, or with its real device and inode but no mark
    of this sweep folder): the bystander lives and the folder stays."""
    import shutil

    from botorl.experiments.backend_local import TRIAL_PID, process_record, sweep_token
    from botorl.experiments.backend_ray import make_ray_temp_dir
    from botorl.experiments.grid import build_grid
    from botorl.experiments.sweep import Sweep, SweepOptions

    out = tmp_path / "sw"
    run_dir = out / "t1" / "wsrl" / "seed0"
    run_dir.mkdir(parents=True)
    bystander = subprocess.Popen(SLEEPER + [str(run_dir.resolve())])
    other = tempfile.mkdtemp(prefix="botorl-ray-", dir="/tmp")  # another sweep's (or anyone's)
    (Path(other) / "keep").write_text("keep me")
    made = make_ray_temp_dir(tmp_path)  # made for another sweep folder
    st = os.lstat(other)
    grid = build_grid(tasks="t1", methods="wsrl", seeds="0")
    try:
        for token in (None, "0" * 32, sweep_token(tmp_path), sweep_token(out)):
            for temp in (other, {"path": other, "dev": st.st_dev, "ino": st.st_ino}, made):
                (out / "sweep.json").write_text(json.dumps({
                    "ray_local_temp_dir": temp, "ray_local_processes": [process_record(bystander.pid, token)]}))
                for p in out.rglob("summary.json"):
                    p.unlink()  # the trial runs again: its pid file is read each time
                (run_dir / TRIAL_PID).write_text(json.dumps({**process_record(bystander.pid, token),
                                                             "host": socket.gethostname()}))
                Sweep(grid, SweepOptions(out=out, backend="sequential", command=fake_command, progress=False)).run()
                assert json.loads((run_dir / "summary.json").read_text())["status"] == "finished"
                assert bystander.poll() is None, (token, temp)
                assert (Path(other) / "keep").read_text() == "keep me" and Path(made["path"]).is_dir(), temp
    finally:
        _stop(bystander)
        shutil.rmtree(other, ignore_errors=True)
        shutil.rmtree(made["path"], ignore_errors=True)


@pytest.fixture(scope="module")
def strangers(tmp_path_factory):
    """A sweep folder, a live bystander working on its trial, another sweep's token for that very
    process, and temp folders that are not this sweep's: one by anyone, one made for another sweep."""
    import shutil

    from botorl.experiments.backend_local import TOKEN_ENV, sweep_token
    from botorl.experiments.backend_ray import make_ray_temp_dir

    root = tmp_path_factory.mktemp("strangers")
    out, elsewhere = root / "sw", root / "other-sweep"
    run_dir = out / "t1" / "wsrl" / "seed0"
    run_dir.mkdir(parents=True)
    elsewhere.mkdir()
    foreign = sweep_token(elsewhere)
    bystander = subprocess.Popen(SLEEPER + [str(run_dir.resolve())], env={**os.environ, TOKEN_ENV: foreign})
    anyones = tempfile.mkdtemp(prefix="botorl-ray-", dir="/tmp")
    made = make_ray_temp_dir(elsewhere)
    yield out, run_dir, bystander, foreign, [anyones, made["path"]]
    _stop(bystander)
    for d in (anyones, made["path"]):
        shutil.rmtree(d, ignore_errors=True)


@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_any_records_a_sweep_folder_holds_stop_and_delete_nothing_not_its_own(strangers, data):
    """A crafted pid file and sweep.json: any pid (the bystander's, this process's, init's), start
    time (real or not), token (none, junk, another sweep's, the form of this folder's) and temp dir
    record (path, device and inode, real or not)."""
    from botorl.experiments.backend_local import TRIAL_PID, own_token, start_time, stop_orphan, sweep_token
    from botorl.experiments.backend_ray import cleanup_previous

    out, run_dir, bystander, foreign, temps = strangers
    pids = st.sampled_from([bystander.pid, os.getpid(), 1, 2 ** 22 + 7])
    token = st.one_of(st.none(), st.text(max_size=40), st.sampled_from([foreign, sweep_token(out), "0" * 32]),
                      st.integers())
    record = st.fixed_dictionaries({"pid": pids, "start": st.one_of(st.just(start_time(bystander.pid)),
                                                                    st.integers(-1, 2 ** 40)), "token": token})
    temp = data.draw(st.sampled_from(temps))
    ident = os.lstat(temp)
    temp_record = st.one_of(st.just(temp), st.fixed_dictionaries({
        "path": st.sampled_from([temp, f"/tmp/botorl-ray-x/../..{temp}", temp + "/"]),
        "dev": st.sampled_from([ident.st_dev, 0]), "ino": st.sampled_from([ident.st_ino, 0])}))
    rec = data.draw(record)
    (run_dir / TRIAL_PID).write_text(json.dumps({**rec, "host": socket.gethostname()}))
    assert not stop_orphan(run_dir, out, timeout=1)
    cleanup_previous({"ray_local_temp_dir": data.draw(temp_record),
                      "ray_local_processes": data.draw(st.lists(record, max_size=3))}, out)
    assert bystander.poll() is None and all(Path(t).is_dir() for t in temps)
    assert not own_token(foreign, out) and own_token(sweep_token(out), out)

"""Run, population and sweep directories are data, never orders (issue 32): whatever they hold,
botorl deletes, signals and writes nothing outside them, reads only regular files of a bounded
size, and answers a bad file with exit 2 and a message -- never a traceback or a hang.

Every test here fails on the code before issue 32 (the control lines show it can fail)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from botorl.cli import main as botorl_main
from botorl.errors import BotorlError

SLEEPER = [sys.executable, "-c", "import time; time.sleep(120)"]


def _smoke_config(*extra: str):
    from botorl.configs.build import build_config

    return build_config(["--task", "pointmaze-umaze", "--profile", "smoke", *extra])


def _crafted_run(d: Path, *extra: str) -> Path:
    """A run directory with a config.json (no training): enough for the readers of resume/eval."""
    from botorl.configs.schema import to_dict

    d.mkdir(parents=True)
    (d / "config.json").write_text(json.dumps(to_dict(_smoke_config(*extra))))
    return d


def _kill(*procs):
    for p in procs:
        if p.poll() is None:
            p.kill()
            p.wait()


# ----------------------------------------------------------------------------- 1. the sweep's Ray cleanup
def test_ray_cleanup_deletes_and_signals_only_what_it_recorded(tmp_path):
    from botorl.experiments.backend_local import process_record
    from botorl.experiments.backend_ray import cleanup_previous, make_ray_temp_dir

    out = tmp_path / "sweep"  # the sweep folder whose sweep.json is read
    out.mkdir()
    ray_dir = tempfile.mkdtemp(prefix="botorl-ray-", dir="/tmp")  # as anyone on the machine can make
    link = Path(tempfile.mkdtemp(prefix="botorl-ray-", dir="/tmp"))
    victim = tmp_path / "precious"
    victim.mkdir()
    (victim / "data").write_text("keep me")
    link.rmdir()
    link.symlink_to(victim)
    needle = f"{ray_dir}/../..{victim}"
    from botorl.experiments.backend_local import TOKEN_ENV, start_time, sweep_token

    bystander = subprocess.Popen(SLEEPER + [needle, str(link)])  # mentions both strings
    # the process an earlier sweep started carries that sweep's secret token (issue 39)
    token = sweep_token(out)
    recorded = subprocess.Popen(SLEEPER, env={**os.environ, TOKEN_ENV: token})
    made = make_ray_temp_dir(out)  # the dir the earlier sweep of `out` made
    try:
        # issue 39: the bystander's real pid and start time (world-readable in /proc), with or
        # without a token, are no order to stop it
        real = {"pid": bystander.pid, "start": start_time(bystander.pid)}
        for manifest in ({"ray_local_temp_dir": needle}, {"ray_local_temp_dir": str(link)},
                         {"ray_local_temp_dir": str(victim)}, {"ray_local_temp_dir": ["/tmp"]},
                         {"ray_local_temp_dir": ray_dir}, {"ray_local_temp_dir": {**made, "path": ray_dir}},
                         {"ray_local_processes": [{"pid": bystander.pid, "start": 1}, {"pid": bystander.pid},
                                                  "x", {"pid": 1, "start": 0}, {"pid": os.getpid(), "start": 0}]},
                         {"ray_local_processes": [real, {**real, "token": token}, {**real, "token": "0" * 32}]}):
            cleanup_previous(manifest, out)
            assert (victim / "data").read_text() == "keep me" and Path(ray_dir).is_dir(), manifest
            assert bystander.poll() is None, manifest
        assert link.is_symlink()
        # control: the dir and the process the earlier sweep did record go
        earlier = {"ray_local_temp_dir": made, "ray_local_processes": [process_record(recorded.pid, token)]}
        cleanup_previous(earlier, out)
        assert not Path(made["path"]).exists() and Path(ray_dir).is_dir()
        assert recorded.wait(timeout=20) != 0
        assert bystander.poll() is None
    finally:
        _kill(bystander, recorded)
        link.unlink(missing_ok=True)
        shutil.rmtree(ray_dir, ignore_errors=True)
        shutil.rmtree(made["path"], ignore_errors=True)


# ----------------------------------------------------------------------------- 1. locks and appenders
def _link_to_precious(tmp_path: Path, at: Path) -> Path:
    target = tmp_path / "precious.txt"
    target.write_text("keep me")
    at.symlink_to(target)
    return target


def test_run_lock_does_not_follow_a_link(tmp_path, capsys):
    d = _crafted_run(tmp_path / "run")
    target = _link_to_precious(tmp_path, d / ".lock")
    assert botorl_main(["eval", str(d)]) == 2
    err = capsys.readouterr().err
    assert "symbolic link" in err and ".lock" in err and "Traceback" not in err
    assert target.read_text() == "keep me"


def test_run_lock_refuses_a_fifo_without_hanging(tmp_path):
    from botorl.pipeline.rundir import RunLock

    d = tmp_path / "run"
    d.mkdir()
    os.mkfifo(d / ".lock")
    with pytest.raises(BotorlError, match="not a regular file"):
        RunLock(d).acquire()


def test_sweep_lock_does_not_follow_a_link(tmp_path):
    from botorl.experiments.grid import build_grid
    from botorl.experiments.sweep import LOCKFILE, Sweep, SweepOptions

    out = tmp_path / "sw"
    out.mkdir()
    target = _link_to_precious(tmp_path, out / LOCKFILE)
    sweep = Sweep(build_grid(tasks="t1", methods="wsrl", seeds="0"), SweepOptions(out=out, progress=False))
    with pytest.raises(BotorlError, match="symbolic link"):
        sweep.run()
    assert target.read_text() == "keep me"


@pytest.mark.parametrize("name", ["metrics/pretrain.csv", "metrics/pretrain.jsonl", "eval.csv"])
def test_log_appenders_do_not_follow_a_link(tmp_path, name):
    from botorl.pipeline.rundir import EVAL_COLUMNS, CsvLog, JsonlLog, RunDir

    run = RunDir(tmp_path / "run")
    run.create()
    target = _link_to_precious(tmp_path, run.root / name)
    with pytest.raises(BotorlError, match="symbolic link"):
        log = JsonlLog(run.root / name) if name.endswith(".jsonl") else CsvLog(run.root / name, EVAL_COLUMNS)
        log.append({"step": 1, "stage": "x", "env_step": 0, "success": 1.0})
    assert target.read_text() == "keep me"


def test_a_linked_metrics_folder_is_refused(tmp_path):
    from botorl.pipeline.rundir import RunDir

    outside = tmp_path / "outside"
    outside.mkdir()
    run = RunDir(tmp_path / "run")
    run.root.mkdir()
    run.metrics.symlink_to(outside)
    with pytest.raises(BotorlError, match="symbolic link"):
        run.create()
    assert list(outside.iterdir()) == []


# ----------------------------------------------------------------------------- 1. population member names
def _crafted_population(out: Path, *extra: str) -> Path:
    """A population directory of two members as `botorl run --seeds 0,1` makes it, before training."""
    from dataclasses import replace

    from botorl.configs.members import population
    from botorl.configs.schema import to_dict
    from botorl.pipeline.rundir import RunDir
    from botorl.pipeline.summary import write_population_file

    cfg = replace(_smoke_config("--seeds", "0,1", *extra), out=str(out))
    members, member_cfgs = population(cfg)
    member_cfgs = [replace(c, out=str(out / m.name)) for c, m in zip(member_cfgs, members)]
    for c in member_cfgs:
        RunDir(c.out).create()
        Path(c.out, "config.json").write_text(json.dumps(to_dict(c)))
    write_population_file(out, cfg, member_cfgs, "running", ["running"] * 2, {})
    return out


def _edit(path: Path, fn) -> None:
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


def test_population_members_stay_inside(tmp_path, capsys):
    from botorl.pipeline.cli import load_population

    pop = _crafted_population(tmp_path / "pop")
    cfg, member_cfgs, runs, _ = load_population(pop)  # control: botorl's own file is read
    assert [r.root.name for r in runs] == ["seed0", "seed1"] and [c.seed for c in member_cfgs] == [0, 1]
    outside = tmp_path / "outside"
    shutil.copytree(pop / "seed1", outside)
    for name in ("../outside", str(outside), "seed1/../../outside", "tb", ""):
        p = tmp_path / f"pop-{len(name)}"
        shutil.copytree(pop, p)
        _edit(p / "population.json", lambda d: d["members"][1].update(name=name))
        assert botorl_main(["resume", str(p), "--no-progress"]) == 2, name
        err = capsys.readouterr().err
        assert "not a member name botorl makes" in err and "Traceback" not in err, err
        assert sorted(x.name for x in outside.iterdir()) == sorted(x.name for x in (pop / "seed1").iterdir())
    # a member folder that is a link out of the population
    p = tmp_path / "pop-link"
    shutil.copytree(pop, p)
    shutil.rmtree(p / "seed1")
    (p / "seed1").symlink_to(outside)
    assert botorl_main(["resume", str(p), "--no-progress"]) == 2
    assert "link out of the population" in capsys.readouterr().err


@pytest.mark.parametrize("edit", [{"task": "pointmaze-medium"}, {"method": "wsrl"}, {"online": {"steps": 7}}])
def test_population_member_config_must_match_the_population(tmp_path, capsys, edit):
    pop = _crafted_population(tmp_path / "pop")

    def change(d):
        for k, v in edit.items():
            d[k].update(v) if isinstance(v, dict) else d.update({k: v})

    _edit(pop / "seed1" / "config.json", change)
    assert botorl_main(["resume", str(pop), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "does not describe a member of the population" in err and "seed1" in err


# ----------------------------------------------------------------------------- 2. a checkpoint knows its run
@pytest.fixture(scope="module")
def two_seeds(tmp_path_factory):
    """Two finished smoke runs, seeds 0 and 1 (BOTO, so alpha matters)."""
    root = tmp_path_factory.mktemp("seeds")
    for seed in (0, 1):
        assert botorl_main(["run", "--task", "pointmaze-umaze", "--profile", "smoke", "--no-progress",
                            "--no-tensorboard", "--online.steps", "40", "--seed", str(seed),
                            "--out", str(root / f"s{seed}")]) == 0
    return root


def _copy_run(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    (dst / ".lock").unlink(missing_ok=True)
    s = json.loads((dst / "summary.json").read_text())
    s["status"] = "running"  # so that resume reads the checkpoints (a finished run has nothing to resume)
    (dst / "summary.json").write_text(json.dumps(s))
    return dst


def _refused(capsys, d: Path, *words: str) -> None:
    for cmd in (["eval", str(d), "--episodes", "1"], ["resume", str(d), "--no-progress"]):
        assert botorl_main(cmd) == 2, cmd
        err = capsys.readouterr().err
        assert "belongs to another run" in err and "Traceback" not in err, err
        assert all(w in err for w in words), (words, err)


def test_another_runs_checkpoints_are_refused(two_seeds, tmp_path, capsys):
    d = _copy_run(two_seeds / "s0", tmp_path / "s0")
    shutil.rmtree(d / "checkpoints")
    shutil.copytree(two_seeds / "s1" / "checkpoints", d / "checkpoints")
    _refused(capsys, d, "seed 1 in the checkpoint, 0 in the config")
    # control: the run's own checkpoints are read
    assert botorl_main(["eval", str(_copy_run(two_seeds / "s0", tmp_path / "own")), "--episodes", "1"]) == 0


def test_export_and_load_policy_refuse_another_runs_checkpoints(two_seeds, tmp_path, capsys):
    """Issue 39: seed 1's checkpoints in seed 0's run were exported with a contract saying seed 0
    and loaded by load_policy; both check the identity as eval does."""
    import botorl

    d = _copy_run(two_seeds / "s0", tmp_path / "s0")
    shutil.rmtree(d / "checkpoints")
    shutil.copytree(two_seeds / "s1" / "checkpoints", d / "checkpoints")
    out = tmp_path / "policy.onnx"
    assert botorl_main(["export", str(d), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "belongs to another run" in err and "seed 1 in the checkpoint, 0 in the config" in err, err
    assert not out.exists()
    for load in (botorl.load_policy, botorl.load_agent):
        with pytest.raises(BotorlError, match="belongs to another run"):
            load(d)
    # control: the run's own checkpoints load
    assert botorl.load_policy(two_seeds / "s0").obs_dim > 0


def test_a_run_whose_data_changed_is_refused(tmp_path, capsys):
    """Issue 39: data.path and the data's size and sha256 are part of the identity every checkpoint
    records; eval and resume refuse a run whose data changed (or whose config.json names other
    data), before the data are loaded."""
    from dataclasses import replace

    from botorl.configs.schema import to_dict
    from botorl.pipeline.checkpoint import full_identity

    data = tmp_path / "logged.npz"
    data.write_bytes(b"the data the run was trained on")
    cfg = _smoke_config()
    cfg = replace(cfg, data=replace(cfg.data, path=str(data)))
    d = tmp_path / "run"
    d.mkdir()
    (d / "config.json").write_text(json.dumps(to_dict(cfg)))
    ck = d / "checkpoints" / "pretrain-final"
    ck.mkdir(parents=True)
    (ck / "state.json").write_text(json.dumps({"stage": "pretrain", "stage_done": True, "step": None,
                                               "done_stages": ["pretrain"], "stage_seconds": {},
                                               "identity": [full_identity(cfg)]}))
    # control: the same data pass the identity (eval then goes on to load them, which this file is not)
    assert botorl_main(["eval", str(d), "--episodes", "1"]) == 2
    err = capsys.readouterr().err
    assert "belongs to another run" not in err and "reads a Minari dataset" in err, err
    data.write_bytes(b"other data, same path")
    for cmd in (["eval", str(d), "--episodes", "1"], ["resume", str(d), "--no-progress"]):
        assert botorl_main(cmd) == 2
        err = capsys.readouterr().err
        assert "the data changed since the run started" in err and "Traceback" not in err, err
    # config.json pointed at other data (a FIFO here): refused, never opened
    os.mkfifo(tmp_path / "fifo.hdf5")
    _edit(d / "config.json", lambda c: c["data"].update(path=str(tmp_path / "fifo.hdf5")))
    assert botorl_main(["resume", str(d), "--no-progress"]) == 2
    assert "not a regular file" in capsys.readouterr().err


@pytest.mark.parametrize("field,value,words", [
    ("seed", 1, "seed 0 in the checkpoint, 1 in the config"),
    ("alpha", 0.5, "alpha -1.0 in the checkpoint, 0.5 in the config"),
    ("method", "wsrl", "method 'boto' in the checkpoint, 'wsrl' in the config"),
    ("task", "pointmaze-medium", "task 'pointmaze-umaze' in the checkpoint, 'pointmaze-medium' in the config"),
    ("online.sac.discount", 0.9, "config '"),
])
def test_an_edited_config_is_refused(two_seeds, tmp_path, capsys, field, value, words):
    d = _copy_run(two_seeds / "s0", tmp_path / "run")

    def edit(cfg):
        *path, last = field.split(".")
        for k in path:
            cfg = cfg[k]
        cfg[last] = value

    _edit(d / "config.json", edit)
    _refused(capsys, d, words)


def test_a_checkpoint_without_identity_is_accepted_with_a_warning(two_seeds, tmp_path, capsys):
    from botorl.pipeline.checkpoint import CheckpointManager

    d = _copy_run(two_seeds / "s0", tmp_path / "old")
    ck = CheckpointManager(d / "checkpoints")
    name = ck.latest()["name"]
    _edit(d / "checkpoints" / name / "state.json", lambda s: s.pop("identity"))
    (d / "checkpoints" / name / "MANIFEST.json").unlink()  # as written before manifests and identities
    assert botorl_main(["eval", str(d), "--episodes", "1", "--checkpoint", name]) == 0
    assert "records no run identity" in capsys.readouterr().err


# ----------------------------------------------------------------------------- 3. bounded by construction
@pytest.mark.parametrize("args,words", [
    (["--seeds", "0-2147483648"], "seeds must lie in [0, 2**31)"),
    (["--seeds", "0-2147483647"], "at most 10,000"),
    (["--alphas", "-1:1:1e-12"], "at most 10,000"),
    (["--seeds", "0-999", "--alphas", "-1:1:0.01"], "members; at most 10,000"),
    (["--online.batch-size", "100000000"], "a batch size must be an integer in [1, 1,048,576]"),
    (["--boto.batch-size", "2000000"], "a batch size must be an integer in [1, 1,048,576]"),
    (["--online.steps", "100000000000"], "more than this machine's"),
    (["--online.buffer-capacity", "100000000000"], "more than this machine's"),
    (["--offline.batch-size", "1000000", "--offline.updates-per-call", "100000"], "more than this machine's"),
    (["--network.critic-hidden-dims", "100000000"], "at most 65,536 units"),
    (["--online.buffer-capacity", "5"], "must hold the warm-up's"),
    # issue 39: the counts the size checks missed
    (["--network.num-critics", "1000000"], "--network.num_critics = 1000000 is invalid: give at most 1,024"),
    (["--offline.cql.cql-n-actions", "1000000000"], "--offline.cql.cql_n_actions = 1000000000 is invalid"),
    (["--offline.cql.num-backup-actions", "1000000000"], "--offline.cql.num_backup_actions = 1000000000 is invalid"),
    (["--online.sac.num-backup-actions", "1000000000"], "--online.sac.num_backup_actions = 1000000000 is invalid"),
    (["--data.steps", "1000000000000000"], "--data.steps = 1000000000000000 is invalid: give at most"),
    (["--network.critic-hidden-dims", "1000000000"], "at most 65,536 units"),
    (["--network.actor-hidden-dims", *["8"] * 65], "1 to 64 layers"),
    (["--data.action-tolerance", "nan"], "--data.action-tolerance = nan is invalid"),
])
def test_sizes_are_refused_before_anything_is_built(tmp_path, capsys, args, words):
    import resource

    out = tmp_path / "out"
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    resource.setrlimit(resource.RLIMIT_AS, (8 << 30, hard))  # a MemoryError, not a swapping machine, on failure
    try:
        assert botorl_main(["run", "--profile", "smoke", "--no-progress", "--out", str(out), *args]) == 2
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err, err
    assert not out.exists()


def test_a_sweep_grid_is_counted_before_it_is_listed(tmp_path):
    from botorl.experiments.grid import build_grid

    with pytest.raises(BotorlError, match="at most 100,000"):
        build_grid(tasks="pointmaze-umaze,pointmaze-medium", methods="boto,wsrl,calql", seeds="0-9999",
                   alphas="-1:1:0.5")


@pytest.mark.parametrize("kind", ["fifo", "dir", "link", "huge", "deep", "bytes"])
@pytest.mark.timeout(60)
def test_a_bad_config_json_is_exit_2(tmp_path, capsys, kind):
    d = _crafted_run(tmp_path / "run")
    cfg = d / "config.json"
    good = cfg.read_bytes()
    cfg.unlink()
    if kind == "fifo":
        os.mkfifo(cfg)  # opening it for reading would block forever
    elif kind == "dir":
        cfg.mkdir()
    elif kind == "link":
        (tmp_path / "elsewhere.json").write_bytes(good)
        cfg.symlink_to(tmp_path / "elsewhere.json")
    elif kind == "huge":  # botorl's own config, padded past the size limit
        cfg.write_bytes(good + b" " * (17 << 20))
    elif kind == "deep":
        cfg.write_bytes(b"[" * 200_000)
    else:
        cfg.write_bytes(b"\xff\xfe" + good)
    for cmd in (["eval", str(d)], ["resume", str(d)]):
        assert botorl_main(cmd) == 2, cmd
        err = capsys.readouterr().err
        assert "config.json" in err and "Traceback" not in err, err


# ----------------------------------------------------------------------------- 6. property tests
# Whatever a file of a run, population or sweep directory holds -- random bytes, a truncation of
# botorl's own file, a link (to a good file outside), a FIFO, a folder, a huge file -- the
# readers of `resume` / `eval` / `sweep` exit 2 with a message or succeed: never a traceback, a
# hang (a FIFO opened for reading blocks without O_NONBLOCK) or a write outside the directory.
# No training runs here: valid inputs lead to "finished already", "no checkpoint yet" or a
# reader called directly.
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

KINDS = ("bytes", "truncated", "link", "fifo", "dir", "huge", "json")
PROPERTY = settings(max_examples=int(os.environ.get("BOTORL_HYPOTHESIS_EXAMPLES", "25")), deadline=None, suppress_health_check=list(HealthCheck))
JSON_VALUES = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
                           lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=8), c, max_size=3),
                           max_leaves=8)


@st.composite
def hostile_file(draw):
    kind = draw(st.sampled_from(KINDS))
    if kind == "bytes":
        return kind, draw(st.binary(max_size=200))
    if kind == "truncated":
        return kind, draw(st.floats(0, 0.999))
    if kind == "json":
        return kind, json.dumps(draw(JSON_VALUES)).encode()
    return kind, None


def _plant(path: Path, kind: str, arg, good: bytes, outside: Path) -> None:
    """Replace the file ``path`` (whose good content is ``good``) by a hostile one."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()
    if kind == "bytes" or kind == "json":
        path.write_bytes(arg)
    elif kind == "truncated":
        path.write_bytes(good[:int(arg * len(good))])
    elif kind == "link":
        target = outside / f"target-{path.name}"
        target.write_bytes(good)
        path.symlink_to(target)
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "dir":
        path.mkdir()
    elif kind == "huge":
        with open(path, "wb") as f:
            f.truncate(80 << 20)


def _snapshot(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file() and not p.is_symlink()}


@pytest.fixture(scope="module")
def hostile_root(tmp_path_factory):
    return tmp_path_factory.mktemp("hostile")


def _case(root: Path) -> tuple[Path, Path]:
    case = Path(tempfile.mkdtemp(dir=root))
    (case / "outside").mkdir()
    (case / "outside" / "keep").write_text("keep me")
    return case, case / "outside"


def _exit_2_or_0(capsys, argv: list[str]) -> None:
    rc = botorl_main(argv)
    err = capsys.readouterr().err
    assert rc in (0, 2), (rc, err[-2000:])
    assert "Traceback" not in err
    if rc == 2:
        assert err.strip(), "exit 2 without a message"


@PROPERTY
@given(f=hostile_file(), cmd=st.sampled_from(["resume", "eval"]))
@pytest.mark.timeout(120)
def test_property_config_json(hostile_root, capsys, f, cmd):
    case, outside = _case(hostile_root)
    d = _crafted_run(case / "run")
    (d / "summary.json").write_text(json.dumps({"status": "finished", "task": "pointmaze-umaze", "method": "boto",
                                                "seed": 0, "alpha": -1.0, "pretrain": "calql"}))
    good = (d / "config.json").read_bytes()
    _plant(d / "config.json", *f, good, outside)
    before = _snapshot(outside)
    _exit_2_or_0(capsys, [cmd, str(d), "--no-progress"] if cmd == "resume" else [cmd, str(d)])
    assert _snapshot(outside) == before


@PROPERTY
@given(f=hostile_file(), which=st.sampled_from(["population.json", "seed1/config.json", "seed0/summary.json"]))
@pytest.mark.timeout(120)
def test_property_population_files(hostile_root, capsys, f, which):
    case, outside = _case(hostile_root)
    pop = _crafted_population(case / "pop")
    _edit(pop / "population.json", lambda d: d.update(status="finished"))
    for m in ("seed0", "seed1"):
        (pop / m / "summary.json").write_text(json.dumps({"status": "finished", "run_dir": str(pop / m)}))
    good = (pop / which).read_bytes()
    _plant(pop / which, *f, good, outside)
    before = _snapshot(outside)
    _exit_2_or_0(capsys, ["resume", str(pop), "--no-progress"])
    assert _snapshot(outside) == before


@PROPERTY
@given(f=hostile_file(), which=st.sampled_from(["latest.json", "state.json", "MANIFEST.json", "agent.ckpt",
                                                "envs.json"]))
@pytest.mark.timeout(120)
def test_property_checkpoint_metadata(hostile_root, f, which):
    """The readers `resume` and `eval` use on a checkpoint folder: latest(), state(), the
    identity check, documents and the agent file's check -- a BotorlError (exit 2) or a result."""
    from botorl.configs.schema import run_identity
    from botorl.pipeline.checkpoint import CheckpointManager, check_identity

    case, outside = _case(hostile_root)
    cfg = _smoke_config()
    ck = CheckpointManager(case / "run" / "checkpoints")
    state = {"identity": [run_identity(cfg)], "stage": "finetune", "step": 10, "stage_done": False,
             "done_stages": ["pretrain"], "stage_seconds": {}, "np_rng": None, "extra": {}, "failed": {}}
    ck.save("finetune-step000000010", state=state, agent=b"agent", save_agent=lambda p, a: Path(p).write_bytes(a),
            documents={"envs": {"x": [1, 2]}})
    folder = ck.root / "finetune-step000000010"
    path = ck.root / which if which == "latest.json" else folder / which
    _plant(path, *f, path.read_bytes(), outside)
    before = _snapshot(outside)
    try:
        latest = ck.latest()
        if latest is not None:
            st_ = ck.state(latest["name"])
            check_identity(st_, [run_identity(cfg)], ck.root, latest["name"])
            ck.document(latest["name"], "envs")
            ck.file(latest["name"], "agent.ckpt")
    except BotorlError:
        pass
    assert _snapshot(outside) == before


@PROPERTY
@given(f=hostile_file())
@pytest.mark.timeout(120)
def test_property_sweep_json(hostile_root, f):
    """sweep.json as the next sweep reads it (cleanup of an earlier Ray instance included)."""
    from botorl.experiments.grid import build_grid
    from botorl.experiments.sweep import Sweep, SweepOptions

    case, outside = _case(hostile_root)
    out = case / "sw"
    sweep = Sweep(build_grid(tasks="t1", methods="wsrl", seeds="0"), SweepOptions(out=out, progress=False))
    out.mkdir()
    sweep._load_manifest()
    sweep.manifest.update(ray_local_temp_dir=f"/tmp/botorl-ray-x/../..{outside}",
                          ray_local_processes=[{"pid": os.getpid(), "start": 0}])
    sweep.save()
    _plant(out / "sweep.json", *f, (out / "sweep.json").read_bytes(), outside)
    before = _snapshot(outside)
    planted = os.lstat(out / "sweep.json")
    try:
        sweep._load_manifest()
        sweep.save()
    except BotorlError:
        # issue 51: a record that cannot be read is left as it was, never replaced by a fresh one
        now = os.lstat(out / "sweep.json")
        assert (now.st_ino, now.st_mode, now.st_size, now.st_mtime_ns) == \
            (planted.st_ino, planted.st_mode, planted.st_size, planted.st_mtime_ns)
    assert _snapshot(outside) == before


# Links (issue 51): any one name botorl writes in a run or sweep directory, or a folder on the
# way to one, made a symbolic link or a hard link to something outside; then every writer of
# that directory runs (no training: the writers on their own). Exit 2 or success, and the
# outside never changes.
RUN_NAMES = (".lock", "config.json", "summary.json", "eval.csv", "curve.png", "metrics", "metrics/pretrain.csv",
             "metrics/pretrain.jsonl", "metrics/q_probe.csv", "checkpoints", "checkpoints/latest.json",
             "checkpoints/pretrain-final", "tb")
SWEEP_NAMES = (".sweep.lock", "sweep.json", "t1", "t1/wsrl", "t1/wsrl/seed0", "t1/wsrl/seed0/sweep-trial.log",
               "t1/wsrl/seed0/sweep-trial-config.json", "t1/wsrl/seed0/summary.json")
FOLDERS = {"metrics", "checkpoints", "checkpoints/pretrain-final", "tb", "t1", "t1/wsrl", "t1/wsrl/seed0"}


def planted_link(names):
    """(name, kind): which name becomes a link, and what kind (a folder cannot be hard-linked)."""
    return st.sampled_from(names).flatmap(lambda n: st.tuples(
        st.just(n), st.sampled_from(["symlink"] if n in FOLDERS else ["symlink", "hardlink"])))


def _plant_link(root: Path, name: str, kind: str, outside: Path) -> None:
    path = root / name
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()
    if name in FOLDERS:
        (outside / "folder").mkdir(exist_ok=True)
        (outside / "folder" / "keep").write_text("keep me")
        path.symlink_to(outside / "folder", target_is_directory=True)
    elif kind == "symlink":
        path.symlink_to(outside / "keep")
    else:
        os.link(outside / "keep", path)


def _make_file(path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("{}\n")


def _outside_state(outside: Path) -> dict:
    return {str(p.relative_to(outside)): (p.stat().st_ino, p.read_bytes())
            for p in sorted(outside.rglob("*")) if p.is_file() and not p.is_symlink()}


@PROPERTY
@given(link=planted_link(RUN_NAMES))
@pytest.mark.timeout(120)
def test_property_links_in_a_run_directory(hostile_root, link):
    from botorl.io import atomic_save_figure, atomic_write_json, pyplot
    from botorl.pipeline.checkpoint import CheckpointManager
    from botorl.pipeline.rundir import EVAL_COLUMNS, CsvLog, MetricsLogger, RunDir, RunLock

    case, outside = _case(hostile_root)
    run = RunDir(case / "run")
    run.create()
    for name in RUN_NAMES:  # every name there first, as a run that stopped leaves them
        (run.root / name).mkdir(parents=True, exist_ok=True) if name in FOLDERS else _make_file(run.root / name)
    _plant_link(run.root, *link, outside)
    before = _outside_state(outside)
    try:
        with RunLock(run.root):
            run.create()
            atomic_write_json(run.config, {"task": "t"}, root=run.root)
            logger = MetricsLogger(run, tensorboard=True)
            logger.log("pretrain", 1, {"loss": 0.5})
            logger.truncate("pretrain", 0)
            logger.close()
            for log in (CsvLog(run.eval_csv, EVAL_COLUMNS, root=run.root),
                        CsvLog(run.metrics / "q_probe.csv", ["stage", "step"], root=run.root)):
                log.append({"stage": "finetune", "step": 1, "env_step": 1, "success": 1.0})
                log.truncate(lambda r: True)
            ck = CheckpointManager(run.checkpoints)
            ck.save("pretrain-final", state={"stage": "pretrain", "stage_done": True}, arrays={"x": {"a": [1.0]}})
            ck.latest()
            fig = pyplot().figure()
            atomic_save_figure(fig, run.curve, root=run.root)
            pyplot().close(fig)
            atomic_write_json(run.summary, {"status": "finished"}, root=run.root)
    except BotorlError as err:
        assert "link" in str(err), err
    assert _outside_state(outside) == before


@PROPERTY
@given(link=planted_link(SWEEP_NAMES))
@pytest.mark.timeout(120)
def test_property_links_in_a_sweep_directory(hostile_root, link):
    """The sweep's own writes (its lock and sweep.json, a trial's folder, config and log) up to the
    launch of the trial, which is a process of its own (`test_hostile_links.py` runs one)."""
    from botorl.experiments.grid import build_grid
    from botorl.experiments.sweep import Sweep, SweepOptions

    case, outside = _case(hostile_root)
    out = case / "sw"
    for name in SWEEP_NAMES:
        (out / name).mkdir(parents=True, exist_ok=True) if name in FOLDERS else _make_file(out / name)
    _plant_link(out, *link, outside)
    before = _outside_state(outside)
    sweep = Sweep(build_grid(tasks="t1", methods="wsrl", seeds="0"),
                  SweepOptions(out=out, progress=False, command=[sys.executable, "-c", "pass"]))
    try:
        with sweep._lock:
            sweep._check_folders()
            sweep._load_manifest()
            sweep.save()
            sweep.prepare(sweep.trials[0])
            sweep.save()
    except BotorlError as err:
        assert "link" in str(err) or "cannot be read" in str(err), err
    assert _outside_state(outside) == before


# ----------------------------------------------------------------------------- 4. every interrupted run resumes
def test_a_damaged_metrics_tail_is_cut_back_on_resume(two_seeds, tmp_path, capsys):
    d = _copy_run(two_seeds / "s0", tmp_path / "run")
    for name in ("metrics/finetune.csv", "metrics/finetune.jsonl", "eval.csv"):
        with open(d / name, "ab") as f:
            f.write(b"999,\xff\xfe\x00 not utf-8\n12")  # a damaged record, then a torn one
    assert botorl_main(["resume", str(d), "--no-progress", "--from", "boto-final"]) == 0
    err = capsys.readouterr().err
    assert "not UTF-8 text and a last line cut short left out" in err
    for name in ("metrics/finetune.csv", "metrics/finetune.jsonl", "eval.csv"):
        data = (d / name).read_bytes()
        assert b"\xff" not in data and data.endswith(b"\n"), name
    steps = [json.loads(x)["step"] for x in (d / "metrics" / "finetune.jsonl").read_text().splitlines()]
    assert steps == sorted(set(steps)) and 999 not in steps
    assert json.loads((d / "summary.json").read_text())["status"] == "finished"


def test_resuming_a_cp_al_snapshot_leaves_the_original_as_it_was(two_seeds, tmp_path, capsys):
    """Issue 51: resuming a `cp -al` snapshot of an interrupted run wrote the original's `.lock`
    (and would have appended to its logs): every file botorl writes in place is first replaced by
    a copy of its own, so the snapshot resumes and the original keeps every byte and inode."""
    orig = _copy_run(two_seeds / "s0", tmp_path / "orig")
    (orig / ".lock").write_text("4242\n")  # the interrupted run's
    snap = tmp_path / "snap"
    subprocess.run(["cp", "-al", str(orig), str(snap)], check=True)

    def state(d):
        return {str(p.relative_to(d)): (p.stat().st_ino, p.read_bytes()) for p in sorted(d.rglob("*")) if p.is_file()}

    before = state(orig)
    assert botorl_main(["resume", str(snap), "--no-progress", "--from", "boto-final"]) == 0
    assert "Traceback" not in capsys.readouterr().err
    assert state(orig) == before
    assert json.loads((snap / "summary.json").read_text())["status"] == "finished"
    assert (snap / ".lock").stat().st_ino != (orig / ".lock").stat().st_ino


def test_resume_hint_names_a_checkpoint_that_passes(two_seeds, tmp_path, capsys):
    d = _copy_run(two_seeds / "s0", tmp_path / "run")
    ck = d / "checkpoints" / "warmup-final"
    (ck / "MANIFEST.json").unlink()  # unverifiable, so the damage shows only when it is read
    (ck / "warmup.npz").write_bytes(b"PK\x03\x04 torn")
    assert botorl_main(["resume", str(d), "--no-progress", "--from", "warmup-final"]) == 2
    err = capsys.readouterr().err
    assert "warmup.npz" in err and "--from pretrain-final" in err and "Traceback" not in err, err


def test_sweep_resumes_pickle_tasks_with_the_users_own_data_path(tmp_path):
    from botorl.configs.schema import to_dict
    from botorl.experiments.grid import build_grid
    from botorl.experiments.sweep import trial_command

    npy = tmp_path / "door2_sparse.npy"
    grid = build_grid(tasks="door-binary-v0", methods="wsrl", seeds="0", profile="smoke",
                      overrides={"data.path": str(npy)})
    trial = grid.trials()[0]
    cfg = grid.config(trial)
    run_dir = tmp_path / "sw" / trial.relpath
    run_dir.mkdir(parents=True)
    (run_dir / "config.json").write_text(json.dumps(to_dict(cfg)))
    action, cmd = trial_command(cfg, run_dir, ["botorl"])
    assert action == "resume" and cmd[-1] == "--allow-pickle", cmd
    # a data path the directory names but this sweep's config does not: no consent
    _edit(run_dir / "config.json", lambda c: c["data"].update(path=str(tmp_path / "other.npy")))
    assert "--allow-pickle" not in trial_command(cfg, run_dir, ["botorl"])[1]


def test_population_resume_does_not_unpickle_what_its_file_names(tmp_path, capsys):
    import builtins

    import numpy as np

    class Payload:
        def __reduce__(self):
            return (builtins.open, (str(tmp_path / "pwned"), "w"))

    evil = tmp_path / "door2_sparse.npy"
    arr = np.empty(1, dtype=object)
    arr[0] = Payload()
    np.save(evil, arr, allow_pickle=True)
    pop = _crafted_population(tmp_path / "pop", "--task", "door-binary-v0", "--data.path", str(evil))
    assert botorl_main(["resume", str(pop), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "pickle" in err and "--allow-pickle" in err and "population.json" in err
    assert not (tmp_path / "pwned").exists()


# ----------------------------------------------------------------------------- 5. every option checked
@pytest.mark.parametrize("args,words", [
    (["--online.sac.actor-lr", "-1e-4"], "a learning rate must be a finite number >= 0"),
    (["--offline.cql.critic-lr", "-3e-4"], "a learning rate must be a finite number >= 0"),
    (["--offline.cql.cql-lagrange-lr", "-1"], "a learning rate must be a finite number >= 0"),
    (["--method", "iql", "--pretrain", "iql", "--offline.iql.value-lr", "-1"], "a learning rate must be"),
    (["--online.sac.log-std-min", "3"], "log_std_min < log_std_max"),
    (["--method", "iql", "--pretrain", "iql", "--offline.iql.log-std-max", "-9"], "log_std_min < log_std_max"),
])
def test_nonsense_settings_are_refused(tmp_path, capsys, args, words):
    out = tmp_path / "out"
    assert botorl_main(["run", "--profile", "smoke", "--no-progress", "--out", str(out), *args]) == 2
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err, err
    assert not out.exists()


@pytest.mark.parametrize("where", ["file", "under-file", "proc"])
def test_out_must_be_a_folder_on_a_disk(tmp_path, capsys, where):
    f = tmp_path / "a-file"
    f.write_text("keep me")
    out = {"file": f, "under-file": f / "run", "proc": Path("/proc/self/botorl-run")}[where]
    for extra in ([], ["--seeds", "0,1"]):
        assert botorl_main(["run", "--profile", "smoke", "--no-progress", "--out", str(out), *extra]) == 2
        err = capsys.readouterr().err
        assert "--out" in err and "Traceback" not in err, err
    assert f.read_text() == "keep me"


def test_a_missing_accelerator_is_a_message(tmp_path):
    env = {**os.environ, "JAX_PLATFORMS": "cuda", "CUDA_VISIBLE_DEVICES": "",
           "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    res = subprocess.run([sys.executable, "-m", "botorl.cli", "run", "--profile", "smoke", "--no-progress",
                          "--out", str(tmp_path / "out")], env=env, capture_output=True, text=True, timeout=300)
    if res.returncode == 0:
        pytest.skip("this machine has a CUDA device")
    assert res.returncode == 2, res.stderr[-2000:]
    assert "JAX_PLATFORMS=cuda" in res.stderr and "Traceback" not in res.stderr


@pytest.mark.parametrize("err", [OSError(28, "No space left on device"),
                                 OSError("Can't synchronously write data (file write failed: time = x, filename = "
                                         "'d.h5', file descriptor = 7, errno = 28, error message = 'No space left "
                                         "on device', buf = 0x1, total write size = 8, bytes this sub-write = 8)")])
def test_a_full_disk_while_writing_a_dataset_is_a_message(tmp_path, capsys, monkeypatch, err):
    from botorl.data import minari_io

    def full(*a, **kw):
        raise err

    monkeypatch.setattr(minari_io, "write_minari", full)
    rc = botorl_main(["data", "generate", "pointmaze-umaze", "--steps", "2000", "--no-progress",
                      "--out", str(tmp_path / "ds")])
    out = capsys.readouterr().err
    assert rc == 2 and "the disk is full" in out and "Traceback" not in out, out


def test_action_tolerance_is_honoured_for_a_minari_path(tmp_path):
    """A Minari --data.path with actions up to |a| = 1.2: refused by default, read with
    --data.action-tolerance 0.5 (the loader judged it with its own 1e-3 before)."""
    from botorl.data.generate import ensure_dataset
    from botorl.data.minari_io import write_minari
    from botorl.envs.registry import get_task
    from botorl.pipeline.runner import load_offline

    from botorl.data.dataset import Dataset

    ds = ensure_dataset("pointmaze-umaze", steps=2000, seed=0, progress=False)
    wide = ds.actions.copy()
    wide[0, 0] = 1.2
    wide_ds = Dataset(ds.observations, wide, ds.rewards, ds.next_observations, ds.terminals,
                      episode_ends=ds.episode_ends, infos=ds.infos, metadata=ds.metadata)
    path = write_minari(wide_ds, path=tmp_path / "wide-v0")
    spec = get_task("pointmaze-umaze")
    with pytest.raises(BotorlError, match="tolerance"):
        load_offline(_smoke_config("--data.path", str(path)), spec)
    got = load_offline(_smoke_config("--data.path", str(path), "--data.action-tolerance", "0.5"), spec)
    assert got.raw_action_max == pytest.approx(1.2)


def test_ctrl_c_during_shutdown_exits_130_quietly():
    """A SIGINT after the command's work, while Python runs its atexit handlers, ends the
    process with 130 and no traceback (it printed a KeyboardInterrupt from the handler)."""
    import subprocess
    import sys

    from helpers import subprocess_env

    code = ("import atexit, os, signal, sys, time\n"
            "atexit.register(lambda: (os.kill(os.getpid(), signal.SIGINT), time.sleep(5)))\n"
            "from botorl import cli\n"
            "sys.argv = ['botorl', '--version']\n"
            "cli.console_main()\n")
    res = subprocess.run([sys.executable, "-c", code], env=subprocess_env(), capture_output=True, text=True, timeout=60)
    assert res.returncode == 130, (res.returncode, res.stderr[-2000:])
    assert "Traceback" not in res.stderr and "KeyboardInterrupt" not in res.stderr, res.stderr[-2000:]
    assert res.stdout.strip()  # the version was printed and flushed


def test_output_into_a_closed_pipe_ends_quietly():
    """`botorl --help | head -1`: a reader that stops early closed the pipe, and the usage's print
    ended in a BrokenPipeError traceback. Here the pipe is closed before the first write."""
    import subprocess
    import sys

    from helpers import subprocess_env

    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        res = subprocess.run([sys.executable, "-m", "botorl.cli", "--help"], env=subprocess_env(), stdout=write_end,
                             stderr=subprocess.PIPE, text=True, timeout=60)
    finally:
        os.close(write_end)
    assert res.returncode == 1 and "Traceback" not in res.stderr and "BrokenPipe" not in res.stderr, res.stderr[-2000:]


def test_export_replaces_only_a_regular_file(tmp_path, capsys):
    """Issue 39: `export --out /dev/null --force` replaced the device with a regular file (as root);
    a FIFO, a link or a folder at --out is refused too, and so is a folder that cannot be written
    (/proc/self), all before any work."""
    d = _crafted_run(tmp_path / "run")
    fifo = tmp_path / "fifo.onnx"
    os.mkfifo(fifo)
    target = _link_to_precious(tmp_path, tmp_path / "link.onnx")
    for out, words in (("/dev/null", "not a regular file"), (str(fifo), "not a regular file"),
                       (str(tmp_path / "link.onnx"), "a link"), (str(tmp_path), "is a folder"),
                       ("/proc/self/x.onnx", "cannot be written")):
        assert botorl_main(["export", str(d), "--out", out, "--force"]) == 2, out
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err, (out, err)
    assert Path("/dev/null").is_char_device() and fifo.is_fifo() and target.read_text() == "keep me"

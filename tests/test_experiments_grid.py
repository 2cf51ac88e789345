"""botorl sweep: the grid (parsing, trial names, each trial's config) and the command line."""

from __future__ import annotations

import pytest

from botorl.configs.members import parse_alphas
from botorl.errors import BotorlError, ConfigError
from botorl.experiments import grid as G
from botorl.experiments.cli import _gather_set, sweep_main


def test_parse_pieces():
    assert G.parse_seeds("0-4") == [0, 1, 2, 3, 4]
    assert G.parse_seeds("0-2,7") == [0, 1, 2, 7]
    assert G.parse_seeds([3, 1]) == [1, 3]
    alphas = parse_alphas("-1:1:0.1", "alphas")
    assert len(alphas) == 21 and alphas[0] == -1.0 and alphas[-1] == 1.0 and alphas[10] == 0.0
    assert alphas[7] == -0.3  # rounded, not -0.30000000000000004
    assert parse_alphas("0.5,-0.3", "alphas") == [0.5, -0.3]
    assert G.parse_methods("boto,wsrl,boto-cql,boto+iql") == [
        ("boto", None), ("wsrl", None), ("boto", "cql"), ("boto", "iql")]
    assert G.parse_overrides(["online.steps=2000", "eval.episodes=-1"]) == {
        "online.steps": "2000", "eval.episodes": "-1"}
    assert G.parse_overrides({"online": {"steps": 2000, "sac": {"utd": 4}}, "x": True}) == {
        "online.steps": "2000", "online.sac.utd": "4", "x": "True"}
    for bad in (lambda: G.parse_seeds("a-b"), lambda: parse_alphas("-2:1:0.5", "alphas"),
                lambda: G.parse_methods("sac"), lambda: G.parse_methods("wsrl-cql"),
                lambda: G.parse_overrides(["online.steps"])):
        with pytest.raises(ConfigError):
            bad()


def test_trials_names_and_arguments():
    grid = G.build_grid(tasks="t1,t2", methods="boto,wsrl,boto-cql", seeds="0-1", alphas="-0.5,0",
                        overrides=["online.steps=2000"], profile="smoke")
    trials = grid.trials()
    # boto and boto-cql: 2 tasks x 2 alphas x 2 seeds each; wsrl: 2 tasks x 2 seeds, no alpha
    assert len(trials) == 8 + 8 + 4
    names = {t.relpath for t in trials}
    assert "t1/boto/alpha-0.50/seed1" in names and "t2/boto-cql/alpha+0.00/seed0" in names
    assert "t1/wsrl/seed0" in names
    assert all(t.alpha is None for t in trials if t.method == "wsrl")
    boto = next(t for t in trials if t.relpath == "t1/boto-cql/alpha-0.50/seed1")
    assert boto.fields == {"task": "t1", "method": "boto", "seed": 1, "alpha": -0.5, "pretrain": "cql"}
    # no --alphas: boto runs with the task's preset alpha
    preset = G.build_grid(tasks="t1", methods="boto", seeds="0").trials()
    assert [t.relpath for t in preset] == ["t1/boto/alpha_preset/seed0"]
    assert preset[0].fields["alpha"] is None


def test_grid_file_and_command_line_merge(tmp_path):
    path = tmp_path / "grid.yaml"
    path.write_text(
        "tasks: [pointmaze-umaze, pointmaze-medium]\nmethods: [boto, wsrl]\nseeds: 0-2\n"
        "alphas: -1:1:0.5\noverrides:\n  online:\n    steps: 3000\nprofile: quick\n"
    )
    grid = G.build_grid(G.load_grid_file(path), seeds="4", overrides=["eval.interval=500"])
    assert grid.tasks == ["pointmaze-umaze", "pointmaze-medium"]
    assert grid.seeds == [4]  # the command line wins
    assert grid.alphas == [-1.0, -0.5, 0.0, 0.5, 1.0]
    assert grid.overrides == {"online.steps": "3000", "eval.interval": "500"}
    assert grid.profile == "quick"
    bad = tmp_path / "bad.yaml"
    bad.write_text("tasks: [a]\nmethod: [boto]\n")
    with pytest.raises(ConfigError, match="unknown field"):
        G.load_grid_file(bad)
    with pytest.raises(ConfigError, match="no seeds"):
        G.build_grid(tasks="a", methods="boto")
    with pytest.raises(ConfigError, match="applies to boto only"):
        G.build_grid(tasks="a", methods="wsrl", seeds="0", alphas="0.5")


def test_sweep_cli_dry_run_and_errors(tmp_path, capsys):
    assert _gather_set(["--set", "a=1", "b=2", "--out", "x", "--set", "c=3"]) == [
        "--out", "x", "--set", "a=1", "b=2", "c=3"]
    out = tmp_path / "sw"
    code = sweep_main(["--tasks", "pointmaze-umaze", "--methods", "boto,wsrl", "--seeds", "0-1",
                       "--alphas", "-1:1:1", "--out", str(out), "--dry-run"])
    assert code == 0
    printed = capsys.readouterr().out
    assert "run     pointmaze-umaze/boto/alpha-1.00/seed0" in printed
    assert "8 trials" in printed
    with pytest.raises(BotorlError, match="unknown task"):
        sweep_main(["--tasks", "no-such-task", "--methods", "boto", "--seeds", "0", "--out", str(out)])
    # a typo in an override fails once, before any trial starts, naming the option
    with pytest.raises(BotorlError, match="online.stepz"):
        sweep_main(["--tasks", "pointmaze-umaze", "--methods", "wsrl", "--seeds", "0", "--out", str(out),
                    "--set", "online.stepz=3"])
    with pytest.raises(BotorlError, match="unknown profile"):
        sweep_main(["--tasks", "pointmaze-umaze", "--methods", "wsrl", "--seeds", "0", "--out", str(out),
                    "--profile", "fast"])
    assert not (out / "sweep.json").exists()


def test_sweep_folder_refuses_other_settings_in_dry_run_too(tmp_path, capsys):
    """A sweep folder's runs share one profile and one set of overrides: another --set is exit 2
    before anything is touched, in --dry-run as in the sweep itself (the dry run used to list the
    earlier trials as "resume", which the sweep then refused)."""
    from botorl.experiments.sweep import Sweep, SweepOptions

    out = tmp_path / "sw"
    out.mkdir()
    grid = G.build_grid(tasks="pointmaze-umaze", methods="wsrl", seeds="0", profile="smoke", overrides=["eval.episodes=3"])
    sweep = Sweep(grid, SweepOptions(out=out, progress=False))
    sweep._load_manifest()
    sweep.save()
    before = (out / "sweep.json").read_bytes()
    args = ["--tasks", "pointmaze-umaze", "--methods", "wsrl", "--seeds", "0", "--profile", "smoke", "--out", str(out)]
    assert sweep_main(args + ["--set", "eval.episodes=3", "--dry-run"]) == 0  # the same settings: listed
    assert "run     pointmaze-umaze/wsrl/seed0" in capsys.readouterr().out
    for extra in (["--dry-run"], []):
        with pytest.raises(BotorlError, match="holds a sweep made with overrides .*eval.episodes.*use another --out"):
            sweep_main(args + ["--set", "eval.episodes=4"] + extra)
    with pytest.raises(BotorlError, match="holds a sweep made with profile 'smoke'"):
        sweep_main(args[:-4] + ["--out", str(out), "--set", "eval.episodes=3", "--dry-run"])
    assert (out / "sweep.json").read_bytes() == before
    assert [p.name for p in out.iterdir() if not p.name.startswith(".")] == ["sweep.json"]  # no trial folder


def test_each_trial_runs_the_config_its_old_command_line_built(tmp_path):
    """A trial's config, built once in the sweep (Grid.config), equals field for field what
    `botorl run` built from the command line sweeps used to give the trial; the trial's
    command reads it back (--config) and sets nothing else but --out and --no-progress."""
    from botorl.configs.build import build_config
    from botorl.configs.schema import to_dict
    from botorl.experiments.sweep import Sweep, SweepOptions

    task = "pointmaze-umaze"
    cases = [  # (grid, population size, each unit's old `botorl run` arguments)
        (G.build_grid(tasks=task, methods="boto", seeds="0-1", alphas="-0.5,0.5", profile="smoke",
                      overrides=["online.steps=60"]), 4,
         [["--task", task, "--method", "boto", "--seeds", "0,1", "--alphas=-0.5,0.5", "--profile", "smoke",
           "--online.steps", "60"]]),
        (G.build_grid(tasks=task, methods="wsrl", seeds="1", profile="smoke",
                      overrides=["pretrain=iql", "tensorboard=False", "boto.log_sigma=-25", "eval.episodes=3"]), 1,
         [["--task", task, "--method", "wsrl", "--seed", "1", "--profile", "smoke", "--pretrain", "iql",
           "--no-tensorboard", "--boto.log_sigma=-25", "--eval.episodes", "3"]]),
        (G.build_grid(tasks=task, methods="boto-cql", seeds="0", alphas="-0.5"), 1,
         [["--task", task, "--method", "boto", "--seed", "0", "--alpha=-0.5", "--pretrain", "cql"]]),
    ]
    for i, (grid, size, old_args) in enumerate(cases):
        (tmp_path / f"sw{i}").mkdir()
        sweep = Sweep(grid, SweepOptions(out=tmp_path / f"sw{i}", population_size=size, progress=False))
        sweep._load_manifest()
        assert len(sweep.trials) == len(old_args)
        for unit, old in zip(sweep.trials, old_args):
            assert to_dict(sweep.config(unit)) == to_dict(build_config(old))
            run_dir, cmd, _ = sweep.prepare(unit)
            args = cmd[cmd.index("run") + 1:]
            assert {a for a in args if a.startswith("-")} == {"--config", "--out", "--no-progress"}
            ran = build_config(args)  # what the trial's `botorl run` runs
            assert to_dict(ran) == to_dict(build_config(old + ["--out", str(run_dir), "--no-progress"]))
    assert ran.pretrain == "cql" and ran.alpha == -0.5

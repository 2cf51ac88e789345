"""`botorl sweep --population-size K`: trials grouped by (task, method, pre-training) into
populations (each a product seeds x alphas), one `botorl run` process (its config's seeds and
alphas) per population under every backend's bookkeeping. A stand-in command speaks the
population protocol (population.json + one ordinary run directory per member); the real
pipeline is tested in test_population_pipeline.py."""

from __future__ import annotations

import json
import sys
import textwrap

import pytest

from botorl.experiments.grid import build_grid, group_populations
from botorl.experiments.sweep import Sweep, SweepOptions, next_action

FAKE_POP = textwrap.dedent(
    """
    import json, sys
    from pathlib import Path
    argv = [a for a in sys.argv[1:] if a != "--no-progress"]
    if argv[0] == "run":
        toks = []
        for t in argv[1:]:
            toks += t.split("=", 1) if t.startswith("--") and "=" in t else [t]
        a = dict(zip(toks[0::2], toks[1::2]))
        out = Path(a["--out"])
        cfg = json.loads(Path(a["--config"]).read_text())
        seeds = [int(s) for s in cfg["seeds"].split(",")]
        alphas = [float(x) for x in cfg["alphas"].split(",")] if cfg["alphas"] else [None]
    else:
        out = Path(argv[1])
        pop = json.loads((out / "population.json").read_text())
        seeds = sorted({m["seed"] for m in pop["members"]})
        alphas = list(dict.fromkeys(m["alpha"] for m in pop["members"]))
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "starts.txt", "a") as f:
        f.write(argv[0] + "\\n")
    members = []
    for al in alphas:
        for s in seeds:
            name = f"seed{s}" if al is None else f"alpha{al:+.2f}-seed{s}"
            members.append({"seed": s, "alpha": al, "name": name})
            d = out / name
            d.mkdir(exist_ok=True)
            (d / "summary.json").write_text(json.dumps({"seed": s, "alpha": al, "status": "finished"}))
    (out / "population.json").write_text(json.dumps({"members": members, "status": "finished"}))
    """
)


def test_group_populations_are_products():
    grid = build_grid(tasks="t1,t2", methods="boto,wsrl,boto-iql", seeds="0-2", alphas="-1,0,0.5,1")
    trials = grid.trials()
    for size in (1, 2, 3, 4, 7, 12, 20):
        jobs = group_populations(trials, size)
        members = [t for j in jobs for t in j.trials]
        assert sorted(t.relpath for t in members) == sorted(t.relpath for t in trials)  # each trial once
        for j in jobs:
            assert 1 <= len(j.trials) <= max(size, 1)
            assert len({(t.task, t.method, t.pretrain) for t in j.trials}) == 1
        assert len({j.relpath for j in jobs}) == len(jobs)
    jobs = group_populations(trials, 6)  # 3 seeds -> 2 alphas per boto population
    boto = [j for j in jobs if j.task == "t1" and (j.method, j.pretrain) == ("boto", None)]
    assert [j.alphas for j in boto] == [(-1.0, 0.0), (0.5, 1.0)]
    assert boto[0].fields == {"task": "t1", "method": "boto", "seeds": "0,1,2", "alphas": "-1,0", "pretrain": None}


@pytest.mark.parametrize("backend", ["sequential", "local"])
def test_sweep_runs_populations(tmp_path, backend):
    fake = tmp_path / "fake_pop.py"
    fake.write_text(FAKE_POP)
    grid = build_grid(tasks="t1", methods="boto,wsrl", seeds="0-2", alphas="-1,1")
    opts = SweepOptions(out=tmp_path / "sw", backend=backend, command=[sys.executable, str(fake)], progress=False,
                        population_size=6)
    sweep = Sweep(grid, opts)
    assert len(sweep.trials) == 2  # boto: 3 seeds x 2 alphas; wsrl: 3 seeds
    manifest = sweep.run()
    assert manifest["counts"] == {"finished": 2}
    for job in sweep.trials:
        d = sweep.run_dir(job)
        assert next_action(d) == "done"
        assert (d / "starts.txt").read_text().split() == ["run"]
        for t in job.trials:
            assert json.loads((tmp_path / "sw" / job.member_dir(t) / "summary.json").read_text())["seed"] == t.seed
    # `botorl report` finds every member's run directory inside the population directories
    from botorl.experiments.runs import find_runs

    runs, skipped = find_runs([tmp_path / "sw"])
    found = sorted(str(r.path) for r in [*runs, *skipped])
    assert len(found) == 9 and not any("never started" in x.reason for x in skipped)
    # the same command again: nothing reruns
    Sweep(grid, opts).run()
    assert all((sweep.run_dir(j) / "starts.txt").read_text().split() == ["run"] for j in sweep.trials)


def test_sweep_cli_population_dry_run(tmp_path, capsys):
    from botorl.experiments.cli import sweep_main

    fake = tmp_path / "fake_pop.py"
    fake.write_text(FAKE_POP)
    code = sweep_main(["--out", str(tmp_path / "sw"), "--tasks", "t1", "--methods", "wsrl", "--seeds", "0-4",
                       "--population-size", "2", "--trial-command", f"{sys.executable} {fake}", "--dry-run"])
    assert code == 0
    out = capsys.readouterr().out
    assert out.count("t1/wsrl/pop-") == 3 and "3 trials" in out

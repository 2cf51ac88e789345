"""benchmarks/against_d3rlpy.py and its worker's command line (no d3rlpy or torch needed: they
load only to time)."""

from __future__ import annotations

import importlib.util
import io
import json
from pathlib import Path

import pytest

from botorl.benchmarks.workloads import WORKLOADS
from botorl.errors import BotorlError


def _script(name: str):
    path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


worker = _script("d3rlpy_worker")
against = _script("against_d3rlpy")


def test_parses_its_options():
    args = worker.parse_args(["--algo", "calql", "--n-critics", "10", "--critic-hidden", "256,256,256,256",
                              "--actor-hidden", "512,512", "--obs-dim", "39", "--action-dim", "28",
                              "--batch", "256", "--n-action-samples", "10", "--utd", "4", "--repeats", "2"])
    assert (args.algo, args.n_critics, args.critic_hidden, args.actor_hidden) == ("calql", 10, [256] * 4, [512, 512])
    assert (args.obs_dim, args.action_dim, args.batch, args.n_action_samples, args.utd) == (39, 28, 256, 10, 4)
    assert not args.serve


@pytest.mark.parametrize("bad", [["--algo", "td3"], ["--critic-hidden", "256,x"], ["--batch", "0"],
                                 ["--n-critics", "-1"], ["--critic-hidden", ""]])
def test_rejects_bad_options(bad):
    with pytest.raises(SystemExit):
        worker.parse_args(bad)


def test_every_workload_spec_round_trips_through_the_command_line():
    for w in WORKLOADS.values():
        if w.d3rlpy_algo is None:
            continue
        spec = against.d3rlpy_spec(w)
        args = worker.parse_args(worker.spec_to_argv(spec))
        assert args.algo == spec["algo"] and args.n_critics == w.num_critics
        assert args.critic_hidden == list(w.critic_hidden) and args.actor_hidden == list(w.actor_hidden)
        assert (args.obs_dim, args.action_dim, args.batch, args.utd) == (w.obs_dim, w.action_dim, w.batch, w.utd)


def test_serve_answers_bad_requests_without_dying(monkeypatch):
    # No torch here: stub the version probe; a bad spec is answered, then quit ends the loop.
    monkeypatch.setattr(worker, "_versions", lambda: {"d3rlpy": "stub"})
    requests = "\n".join([json.dumps({"cmd": "setup", "name": "x", "spec": {"algo": "nope"}}),
                          json.dumps({"cmd": "frobnicate"}), json.dumps({"cmd": "quit"})]) + "\n"
    out = io.StringIO()
    assert worker.serve(io.StringIO(requests), out) == 0
    answers = [json.loads(line) for line in out.getvalue().splitlines()]
    assert answers[0]["ready"] and answers[1]["ok"] is False and "bad spec" in answers[1]["error"]
    assert answers[2]["ok"] is False and answers[3] == {"ok": True}


def test_a_bad_workload_is_refused_before_any_venv_is_made(monkeypatch):
    monkeypatch.setattr(against, "ensure_venv", lambda: pytest.fail("made the venv"))
    with pytest.raises(BotorlError, match="unknown workload"):
        against.main(["--only", "nope"])

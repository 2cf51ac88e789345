"""The online loop keeps the device busy (issue 41): no implicit host<->device transfer while
fine-tuning acts, learns and evaluates; a population's evaluation is one lockstep over all its
members' envs; and the jitted dispatches of one online env step, counted.

Two smoke runs through the real pipeline (`botorl run`, ~20 s each on 2 cores): BOTO on seed 0
alone, and the population of seed 0 at two alphas (its members split over the 2 CPU devices
where there are 2). Members of one seed share the pre-training, so until BOTO their policies are
the run alone's: the step-0 evaluation of the pair must step exactly the envs of one member's,
with one policy call per env step for both.
"""

from __future__ import annotations

import contextlib

import jax
import numpy as np
import pytest

from botorl.agents import population
from botorl.cli import main as botorl_main
from botorl.pipeline import online, runner

# the jitted programs an online step or an evaluation may dispatch (agents/population.py)
PROGRAMS = ("jit_sample", "jit_eval", "jit_q_mean", "jit_update", "jit_update_many", "jit_update_masked",
            "jit_update_many_on_device", "jit_act_after_update", "jit_act_after_update_many")


class Probe:
    """Counts while a run runs: each program's dispatches (per online step), each evaluation's
    policy calls and their observation shapes; fine-tuning's steps and evaluations under
    ``jax.transfer_guard("disallow")``."""

    def __init__(self, monkeypatch):
        self.dispatches: dict[str, int] = {}
        self.steps: list[dict[str, int]] = []  # per online step: program -> dispatches
        self.evaluations: list[dict] = []
        self.precisions: set = set()  # JAX's default matmul precision while fine-tuning steps
        for name in PROGRAMS:
            if hasattr(population, name):
                monkeypatch.setattr(population, name, self._counted(name, getattr(population, name)))
        advance, evaluate, episodes = online.OnlineState.advance, runner.RunContext.evaluate, runner.evaluation.run_episodes

        def guarded_advance(state, agents, window):
            self.precisions.add(jax.config.jax_default_matmul_precision)
            before = dict(self.dispatches)
            with jax.transfer_guard("disallow"):
                out = advance(state, agents, window)
            self.steps.append({k: v - before.get(k, 0) for k, v in self.dispatches.items() if v - before.get(k, 0)})
            return out

        def guarded_evaluate(ctx, agents, env_step):
            guard = jax.transfer_guard("disallow") if ctx._stage == "finetune" else contextlib.nullcontext()
            with guard:
                return evaluate(ctx, agents, env_step)

        def counted_episodes(policy, envs, **kw):
            rec = {"members": len(envs), "calls": 0, "shapes": set()}

            def counted(obs):
                rec["calls"] += 1
                rec["shapes"].add(np.shape(obs))
                return policy(obs)

            stats = episodes(counted, envs, **kw)
            rec["lengths"] = [s.length for s in stats]
            self.evaluations.append(rec)
            return stats

        monkeypatch.setattr(online.OnlineState, "advance", guarded_advance)
        monkeypatch.setattr(runner.RunContext, "evaluate", guarded_evaluate)
        monkeypatch.setattr(runner.evaluation, "run_episodes", counted_episodes)

    def _counted(self, name, fn):
        def call(*a, **k):
            self.dispatches[name] = self.dispatches.get(name, 0) + 1
            return fn(*a, **k)
        return call


@pytest.fixture(scope="module")
def probes(tmp_path_factory):
    root = tmp_path_factory.mktemp("online-device")
    out = {}
    for name, args in (("alone", ["--seed", "0"]), ("pair", ["--seeds", "0", "--alphas=-0.5,0.5"])):
        with pytest.MonkeyPatch.context() as mp:
            probe = Probe(mp)
            code = botorl_main(["run", "--task", "pointmaze-umaze", "--method", "boto", "--profile", "smoke",
                                "--no-progress", "--no-tensorboard", "--out", str(root / name), *args])
            assert code == 0, f"{name}: a transfer the guard refused, or another failure (exit {code})"
        probe.root = root / name
        out[name] = probe
    return out


def test_fine_tuning_and_its_evaluations_run_under_the_transfer_guard(probes):
    """Every online step (act, env step, buffer, UTD update) and every evaluation in fine-tuning ran
    under jax.transfer_guard("disallow"): observations, batches and keys travel by explicit
    device_put / device_get only, and nothing of the agents moves between devices per call."""
    for name, p in probes.items():
        # the smoke profile: 40 online steps, 30 of them the warm-up, which is the same loop
        # (OnlineState.advance with learning off), so its steps ran under the guard too
        assert len(p.steps) == 40, name
        assert sum(1 for e in p.evaluations) >= 3, name  # step 0 (warm-up), fine-tuning's start and end


def test_the_run_computes_at_its_configs_precision(probes):
    """Every step ran inside the run's precision scope (the default, tf32: JAX's "tensorfloat32")."""
    for name, p in probes.items():
        assert p.precisions == {"tensorfloat32"}, name


def test_a_populations_evaluation_is_one_lockstep_over_all_its_members_envs(probes):
    alone, pair = probes["alone"].evaluations, probes["pair"].evaluations
    assert [e["members"] for e in alone] == [1] * len(alone) and [e["members"] for e in pair] == [2] * len(pair)
    # every call carries all members' envs: (N, E, O)
    assert all(s[:1] == (2,) and len(s) == 3 for e in pair for s in e["shapes"])
    # step 0: both members are the pre-trained policy of seed 0, the run alone's; its episodes,
    # stepped for both members at once, take exactly as many policy calls as for one member
    assert pair[0]["lengths"] == alone[0]["lengths"] * 2
    assert pair[0]["calls"] == alone[0]["calls"] > 0
    # and never more calls than the longest round of episodes: one call per env step
    for e in alone + pair:
        assert e["calls"] <= max(e["lengths"]) * 2  # smoke: 2 episodes on 2 envs, one round; lengths are means


def test_dispatches_per_online_step(probes):
    """One online env step of learning members is one jitted dispatch: the UTD update and the
    next step's policy call are one program (the first step of fine-tuning draws its action on
    its own); the observations and the batch travel by explicit transfers. The warm-up's steps
    (learning off) are one policy call each. N members, the same."""
    for name, p in probes.items():
        assert p.steps[:30] == [{"jit_sample": 1}] * 30, name
        assert p.steps[30] == {"jit_sample": 1, "jit_act_after_update": 1}, name
        assert p.steps[31:] == [{"jit_act_after_update": 1}] * (len(p.steps) - 31), name
    assert probes["alone"].steps == probes["pair"].steps  # the same programs for 2 members as for 1


def test_bench_paper_times_a_populations_evaluation_as_the_run_does(probes, tmp_path):
    """`bench --paper`'s timed evaluation, in its own measured process: both members' last
    checkpoints, their envs in one lockstep, one policy call per env step for both; the device's
    memory where it has its own (None on a CPU: the arrays are host memory)."""
    import json

    from botorl.benchmarks import paper as PB

    log = tmp_path / "eval.log"
    try:  # _run raises when the measured process exits non-zero
        wall, rss, ev = PB._run(["--time-eval", str(probes["pair"].root), "2", "2"], log, "the timed evaluation")
    except RuntimeError as e:
        pytest.fail(f"{e}\n{log.read_text()[-2000:]}")
    assert ev == json.loads(log.with_suffix(".stats.json").read_text())
    assert ev["members"] == 2 and ev["episodes"] == 2 and ev["precision"] == "tf32" and rss > 0
    # one call per lockstep env step: as many as the longest episode, never one per member's step
    assert 0 < ev["episode_length"] <= ev["policy_calls"] <= ev["env_steps"]
    assert ev["env_steps"] == pytest.approx(2 * ev["episode_length"] * 2)
    assert ev["device_peak_mb"] is None and ev["seconds"] > 0

"""JSON of a quick run of one tiny workload, without d3rlpy (no timing is asserted)."""

from __future__ import annotations

import json

import pytest

from botorl.benchmarks.suite import BenchConfig, format_table, main, run, write_json
from botorl.errors import BotorlError

UPDATE_KEYS = {"botorl_updates_per_s", "d3rlpy_updates_per_s", "ratio", "gflops", "peak_fraction",
               "flops_per_update", "flops_per_update_xla", "label", "shapes"}


@pytest.fixture(scope="module")
def result():
    return run(BenchConfig(quick=True, tiny=True, only="sac2", loop=False, repeats=1, min_time=0.05))


def test_schema(result, tmp_path):
    assert set(result) >= {"schema", "machine", "matmul_peak_gflops", "updates", "online_loop_efficiency"}
    assert list(result["updates"]) == ["sac2"]
    row = result["updates"]["sac2"]
    assert UPDATE_KEYS <= set(row)
    assert row["botorl_updates_per_s"] > 0 and row["gflops"] > 0 and 0 < row["peak_fraction"]
    # Without --against the d3rlpy columns are empty, not made up.
    assert row["d3rlpy_updates_per_s"] is None and row["ratio"] is None
    assert result["online_loop_efficiency"] is None
    # The counter finds the update's matmuls (forward and backward), and more work besides.
    assert 0 < row["matmul_flops_per_update"] < row["flops_per_update"]
    assert "SAC step" in format_table(result)
    path = tmp_path / "sub" / "bench.json"
    write_json(result, str(path))
    assert json.loads(path.read_text())["updates"]["sac2"]["flops_per_update"] == row["flops_per_update"]


def test_unknown_workload_is_a_user_error():
    with pytest.raises(BotorlError, match="unknown workload"):
        main(["--only", "nope"])


@pytest.mark.slow  # ~25 s: a benchmark's workload; test_schema runs the others
def test_online_loop_times_the_fine_tuning_loop():
    """The loop benchmark runs fine-tuning's own step (OnlineState.advance): every env step
    lands in the replay buffer and updates the agent."""
    import jax
    import numpy as np

    from botorl.agents.sac import SACAgent, SACConfig
    from botorl.benchmarks.online_loop import OnlineLoop
    from botorl.envs.registry import get_task

    spec = get_task("pointmaze-umaze")
    agent = SACAgent.create(SACConfig(actor_hidden_dims=(8,), critic_hidden_dims=(8,), num_critics=2),
                            spec.obs_dim, spec.action_dim, 0)
    loop = OnlineLoop(agent, spec, batch=4, utd=2, prefill=10)
    with loop.state:
        loop.run(3)
    assert loop.state.step == 3 and len(loop.state.buffer) == 13
    before, after = jax.tree_util.tree_leaves(agent.critic.params), jax.tree_util.tree_leaves(loop.agents.critic.params)
    assert any(not np.allclose(np.asarray(b), np.asarray(a)[0]) for b, a in zip(before, after))

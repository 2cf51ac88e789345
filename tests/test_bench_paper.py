"""botorl bench --paper: the projection's arithmetic and the metrics it reads, by hand (the
benchmark itself runs the full profile, far too long for the suite)."""

from __future__ import annotations

import pytest

from botorl.benchmarks import paper as PB
from botorl.configs.presets import make_preset
from botorl.configs.resolve import resolve


def test_steady_rate_skips_the_compiling_first_row():
    # rows every 10 updates; the first interval took 10 s (compile), then 2 updates/s
    rows = [{"step": "10", "steps_per_s": "1.0"}, {"step": "20", "steps_per_s": "2.0"},
            {"step": "30", "steps_per_s": "2.0"}, {"step": "40", "steps_per_s": "2.0"}]
    rate, compile_s = PB._steady(rows, "step", "steps_per_s")
    assert rate == 2.0 and compile_s == pytest.approx(10 - 10 / 2)
    # BOTO logs cumulative seconds: 100 steps at 1.5 s, then 100 more every 0.5 s
    boto = [{"step": str(100 * k), "seconds": str(1.5 + 0.5 * (k - 1))} for k in range(1, 5)]
    rate, compile_s = PB._steady(boto, "step", None, "seconds")
    assert rate == pytest.approx(200.0) and compile_s == pytest.approx(1.0)


def test_fine_tuning_compile_time_counts_from_the_end_of_the_warm_up():
    """Fine-tuning logs on the online axis, which starts after the 500-step warm-up: its first
    row (step 525) covers 25 steps, not 525 (issue 41: the 313 s of 'compile' an H100 gave were
    21 times its real figure)."""
    rows = [{"step": str(525 + 25 * k), "env_steps_per_s": str(1.0 if k == 0 else 5.0)} for k in range(4)]
    rate, compile_s = PB._steady(rows, "step", "env_steps_per_s", start=500)
    assert rate == 5.0 and compile_s == pytest.approx(25 - 25 / 5)  # 20 s: 25 steps in 25 s, 5 s of them steady
    _, counted_from_0 = PB._steady(rows, "step", "env_steps_per_s")
    assert counted_from_0 == pytest.approx(525 - 525 / 5)  # what it said before: 420 s


def test_projection_of_the_antmaze_paper_budget_by_hand():
    cfg = resolve(make_preset("antmaze-large-diverse-local", "full", "boto"))
    budget = PB.paper_budget(cfg, horizon=1000)
    # Cal-QL 1M, warm-up 5k, Table 2's 100k BOTO steps, 300k online steps of which 5k warm-up,
    # 61 evaluations (step 0 and every 5k) of 20 episodes of 1,000 steps
    assert budget == {"pretrain": 1_000_000, "warmup": 5_000, "boto": 100_000, "finetune": 295_000,
                      "eval": 61 * 20 * 1000}
    stages = {"pretrain": {"rate": 100.0, "compile_s": 36.0}, "warmup": {"rate": 1000.0, "compile_s": 0.0},
              "boto": {"rate": 500.0, "compile_s": 0.0}, "finetune": {"rate": 50.0, "compile_s": 0.0},
              "eval": {"rate": 12_200.0, "compile_s": 0.0}}
    # 10,036 + 5 + 200 + 5,900 + 100 = 16,241 s
    p = PB.project(stages, budget)
    assert p["projected_hours"] == pytest.approx(16_241 / 3600)
    assert p["share"]["pretrain"] == pytest.approx(10_036 / 16_241) and sum(p["share"].values()) == pytest.approx(1)
    two = PB.project(stages, budget, members=2)  # a population evaluates each member
    assert two["projected_hours"] == pytest.approx(16_341 / 3600) and two["hours_per_run"] == pytest.approx(16_341 / 7200)


def test_bad_input_exits_2_before_any_run(capsys):
    from botorl.cli import main as botorl_main

    assert botorl_main(["bench", "--paper", "--tasks", "no-such-task"]) == 2
    assert "no-such-task" in capsys.readouterr().err
    assert botorl_main(["bench", "--paper", "--members", "1,x"]) == 2
    assert "--members" in capsys.readouterr().err
    assert botorl_main(["bench", "--paper", "--pretrain-steps", "2"]) == 2
    assert "--pretrain-steps 2 is too small" in capsys.readouterr().err


@pytest.mark.parametrize("task", ["kitchen-partial-v0", "pen-binary-v0"])
def test_synthetic_data_is_read_by_the_tasks_own_loader(task, tmp_path):
    """kitchen reads Minari datasets and pen Cal-QL .npy files: the benchmark's synthetic rows
    must come in that format (they once came as a D4RL hdf5, which `botorl run` refused)."""
    from botorl.data.tasks import load_task_data
    from botorl.envs.registry import get_task

    spec = get_task(task)
    run_args, eval_args = PB._synthetic_data(spec, tmp_path, rows=4 * spec.max_episode_steps)
    path = run_args[run_args.index("--data.path") + 1]
    ds = load_task_data(spec, path)
    assert ds.obs_dim == spec.obs_dim and ds.action_dim == spec.action_dim
    assert len(ds.rewards) == 4 * spec.max_episode_steps  # every row kept (pen: every episode ends in success)
    assert eval_args == (["--allow-pickle"] if spec.dataset_source.kind == "calql_npy" else [])


def test_the_json_names_the_device():
    """The machine's description: the device JAX runs on by name and backend (a CPU here), and
    its memory limit (None on a CPU, whose arrays are host memory)."""
    import jax

    m = PB.machine()
    assert m["backend"] == jax.default_backend() and m["device_kind"] == jax.devices()[0].device_kind
    assert m["device_count"] >= 1 and m["jax"] == jax.__version__
    assert PB.device_memory() == {"device_peak_mb": None, "device_limit_mb": None} or jax.default_backend() != "cpu"

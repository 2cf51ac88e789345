"""The matmul precision policy (``RunConfig.precision``; docs/performance.md, "Precision"):
the field, its check, what it does to every matmul of an update, and the member-vs-alone
tolerance the GPU tests derive from it. Nothing here trains: every update is only lowered."""

from __future__ import annotations

import json
import re

import jax
import numpy as np
import pytest

from botorl.cli import main as botorl_main
from botorl.configs.presets import make_preset
from botorl.configs.resolve import resolve, validate
from botorl.configs.schema import _digest, flatten, run_identity, to_dict
from botorl.errors import ConfigError
from botorl.jaxsetup import MATMUL_ROUNDOFF, check_precision, matmul_precision, member_tolerance


def test_default_is_tf32_and_leaves_the_run_identity_as_before_the_field():
    cfg = resolve(make_preset("pointmaze-umaze", "smoke", "boto"))
    assert cfg.precision == "tf32"
    # a run made before the field existed (JAX's default on a GPU is TF32, on a CPU fp32 either
    # way) must keep its identity, or `botorl resume` would refuse its checkpoints
    flat = {k: v for k, v in flatten(to_dict(cfg)).items() if k != "precision"}
    old = run_identity(cfg)["config"]
    from botorl.configs.schema import _NOT_STATE

    kept = {k: v for k, v in flat.items()
            if k not in _NOT_STATE and not k.startswith(("eval.", "metric.")) and not k.endswith("log_every")}
    # and the agents' former copies of the UTD, kept at their values for the same reason
    # (test_pipeline_config.py::test_a_config_file_from_before_the_utd_left_the_agents_still_runs)
    kept.update({"online.sac.utd_ratio": cfg.online.utd, "offline.cql.utd_ratio": 1})
    assert old == _digest(kept)
    # another precision computes other numbers: another run
    cfg.precision = "highest"
    assert run_identity(cfg)["config"] != old


def test_bad_precision_is_exit_2_on_the_command_line_and_in_a_config_file(tmp_path, capsys):
    assert botorl_main(["run", "--profile", "smoke", "--precision", "fp8", "--out", str(tmp_path / "r")]) == 2
    assert "precision" in capsys.readouterr().err and not (tmp_path / "r").exists()
    cfg = resolve(make_preset("pointmaze-umaze", "smoke", "boto"))
    cfg.precision = "fp8"
    with pytest.raises(ConfigError, match="precision .fp8. is not one of highest, tf32, bf16"):
        validate(cfg)
    doc = to_dict(resolve(make_preset("pointmaze-umaze", "smoke", "boto")))
    doc["precision"] = "half"
    (tmp_path / "cfg.json").write_text(json.dumps(doc))
    assert botorl_main(["run", "--config", str(tmp_path / "cfg.json"), "--out", str(tmp_path / "r2")]) == 2
    assert "precision = 'half'" in capsys.readouterr().err


def test_member_tolerance_follows_the_input_roundoff():
    assert [check_precision(p) for p in ("highest", "tf32", "bf16")] == ["highest", "tf32", "bf16"]
    # fp32 keeps the bound the GPU test had; TF32 (10 stored mantissa bits) and bf16 (7) get
    # twice their unit roundoff, above the 2.0e-4 an H100 measured at JAX's default (TF32)
    assert member_tolerance("highest") == 1e-4
    assert member_tolerance("tf32") == pytest.approx(2 * 2.0**-11) and member_tolerance("tf32") > 2.0e-4
    assert member_tolerance("bf16") == pytest.approx(2 * 2.0**-8)
    assert MATMUL_ROUNDOFF["highest"] < MATMUL_ROUNDOFF["tf32"] < MATMUL_ROUNDOFF["bf16"]
    with pytest.raises(ConfigError):
        member_tolerance("fp16")


def _dots(text: str) -> list[tuple[str, bool]]:
    """Each dot_general of a lowered (StableHLO) program: (its line, whether it is one of
    LayerNorm's row statistics: a product with a column, ``(..., n) x (n, 1)``)."""
    lines = [ln for ln in text.splitlines() if "stablehlo.dot_general" in ln]
    return [(ln, bool(re.search(r", tensor<\d+x1xf32>\) ->", ln))) for ln in lines]


@pytest.mark.parametrize("precision, want", [("highest", "precision = [HIGHEST, HIGHEST]"),
                                             ("tf32", "precision = [HIGH, HIGH]"),
                                             ("bf16", "algorithm = <lhs_precision_type = bf16")])
def test_every_matmul_of_an_update_runs_at_the_precision(precision, want):
    """The SAC update (critics with LayerNorm, actor, temperature) lowered under the policy: every
    dot carries it, except LayerNorm's row statistics, which ask for HIGHEST themselves."""
    from botorl.agents.common import jit_agent_update
    from botorl.agents.sac import SACAgent, SACConfig

    agent = SACAgent.create(SACConfig(actor_hidden_dims=(8, 8), critic_hidden_dims=(8, 8), num_critics=2,
                                      critic_layer_norm=True), obs_dim=3, action_dim=2, seed=0)
    rng = np.random.default_rng(0)
    batch = {"observations": rng.normal(size=(4, 3)).astype(np.float32), "actions": np.zeros((4, 2), np.float32),
             "rewards": np.zeros(4, np.float32), "next_observations": rng.normal(size=(4, 3)).astype(np.float32),
             "dones": np.zeros(4, np.float32), "mc_returns": np.zeros(4, np.float32)}
    with matmul_precision(precision):
        dots = _dots(jit_agent_update.lower(agent, batch).as_text())
    layers = [ln for ln, stats in dots if not stats]
    assert len(layers) >= 16  # forward and backward of actor and critics
    assert all(want in ln for ln in layers), [ln for ln in layers if want not in ln][:2]
    assert all("precision = [HIGHEST, HIGHEST]" in ln for ln, stats in dots if stats)
    # and outside the policy's scope the dots are JAX's default, as before the field
    assert all("precision = [DEFAULT, DEFAULT]" in ln and "algorithm" not in ln
               for ln, stats in _dots(jit_agent_update.lower(agent, batch).as_text()) if not stats)


def test_a_config_file_from_before_the_field_still_runs(tmp_path):
    """`botorl run --config FILE` of a file a sweep wrote before the field (no "precision"): the
    run computes at tf32, what it computed then; any other missing field is still refused."""
    from botorl.configs.build import build_config

    doc = to_dict(resolve(make_preset("pointmaze-umaze", "smoke", "boto")))
    del doc["precision"]
    (tmp_path / "old.json").write_text(json.dumps(doc))
    assert build_config(["--config", str(tmp_path / "old.json")]).precision == "tf32"
    del doc["seed"]
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(ConfigError, match="not every field"):
        build_config(["--config", str(tmp_path / "bad.json")])

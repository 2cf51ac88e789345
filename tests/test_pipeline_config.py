"""Presets, the CLI's config parsing, and the bad-configuration errors (exit code 2).

No training here: every bad configuration must fail before any work (no run directory).
"""

from __future__ import annotations

from dataclasses import replace

import re

import pytest

from botorl.cli import main as botorl_main
from botorl.configs.presets import PROFILES, QUICK_POINTMAZE_PRETRAIN, make_preset
from botorl.configs.resolve import resolve, validate
from botorl.configs.schema import RunConfig, from_dict, to_dict
from botorl.envs.registry import get_task
from botorl.pipeline.cli import build_config
from botorl.configs.methods import METHODS
from botorl.errors import ConfigError

PAPER_TASKS = ["antmaze-large-diverse-v2", "antmaze-large-play-v2", "kitchen-partial-v0", "kitchen-mixed-v0",
               "door-binary-v0", "pen-binary-v0"]
GENERATED = ["pointmaze-umaze", "pointmaze-medium", "pointmaze-large", "door-binary-local"]


@pytest.mark.parametrize("task", PAPER_TASKS)
def test_full_preset_is_the_papers(task):
    cfg = resolve(make_preset(task, "full", "boto"))
    validate(cfg)
    spec = get_task(task)
    assert cfg.alpha == spec.paper.alpha and not hasattr(cfg.boto, "alpha")
    assert cfg.boto.boto_steps == spec.paper.boto_steps and cfg.boto.log_sigma == spec.paper.log_sigma
    assert cfg.online.steps == 300_000 and cfg.online.utd == 4 and cfg.online.offline_ratio == 0.0
    assert cfg.network.num_critics == 10 and cfg.online.sac.num_critics == 10 and cfg.offline.cql.num_critics == 10
    assert cfg.offline.cql.calql and cfg.pretrain == "calql"
    assert cfg.eval.episodes == 20 and cfg.warmup.steps == 5_000
    # algorithms.md section 5: networks and pre-training length per domain
    want = {"antmaze": ((256,) * 4, (256,) * 2, 1_000_000), "adroit": ((512,) * 3, (512,) * 2, 20_000),
            "kitchen": ((512,) * 3, (512,) * 3, 250_000)}[spec.domain]
    assert (cfg.online.sac.critic_hidden_dims, cfg.online.sac.actor_hidden_dims, cfg.offline.steps) == want
    assert cfg.offline.cql.critic_hidden_dims == want[0]
    assert cfg.online.sac.max_target_backup == (spec.domain == "antmaze")
    assert cfg.offline.cql.cql_weight == {"antmaze": 5.0, "adroit": 1.0, "kitchen": 5.0}[spec.domain]
    assert cfg.offline.cql.cql_lagrange == (spec.domain == "antmaze")


@pytest.mark.parametrize("task", GENERATED)
@pytest.mark.parametrize("profile", PROFILES)
def test_every_generated_preset_validates(task, profile):
    for method in METHODS:
        cfg = resolve(make_preset(task, profile, method))
        validate(cfg)
        assert cfg.task == task and cfg.profile == profile and cfg.method == method


def test_method_table_settings():
    base = "pointmaze-umaze"
    adim = get_task(base).action_dim
    for m in ("calql", "cql", "iql"):
        # the baselines as WSRL ran them: their own 2 critics without LayerNorm, UTD 1, 50/50
        cfg = resolve(make_preset(base, "full", m))
        assert cfg.pretrain == m and cfg.online.utd == 1 and cfg.online.offline_ratio == 0.5 and cfg.alpha is None
        agent_cfg = cfg.offline.iql if m == "iql" else cfg.offline.cql
        assert agent_cfg.num_critics == 2 and not agent_cfg.critic_layer_norm and not agent_cfg.actor_layer_norm
    assert resolve(make_preset("kitchen-mixed-v0", "full", "calql")).online.offline_ratio == 0.25
    for m in ("calql", "cql"):
        for profile in ("quick", "full"):
            # WSRL runs its 2-critic baselines without a critic subset: the penalty on both
            # critics, the target the min of both (not a pair drawn with replacement)
            cql = resolve(make_preset(base, profile, m)).offline.cql
            assert cql.cql_penalty_critics is None and cql.num_critics == 2
            assert cql.num_min_critics == 2 and not cql.subsample_replace
    rlpd = resolve(make_preset(base, "full", "rlpd"))
    assert rlpd.pretrain is None and rlpd.online.random_steps == 5_000 and rlpd.online.offline_ratio == 0.5
    assert rlpd.online.utd == 4 and rlpd.online.sac.target_entropy == -adim / 2
    assert rlpd.online.sac.actor_objective == "mean" and not rlpd.online.sac.subsample_replace
    assert rlpd.online.sac.num_critics == 10 and rlpd.online.sac.critic_layer_norm
    # antmaze (and pointmaze, which takes its settings): one critic in RLPD's target, max backup
    assert rlpd.online.sac.num_min_critics == 1 and rlpd.online.sac.max_target_backup
    assert resolve(make_preset("door-binary-v0", "full", "rlpd")).online.sac.num_min_critics == 2
    for m in ("boto", "wsrl"):
        cfg = resolve(make_preset(base, "full", m))
        # WSRL: 10 critics pre-trained and fine-tuned, penalty on a random pair, target entropy
        # -|A| in fine-tuning (its sac_config's 0.0, which its SAC agent turns into -|A| since
        # f73d11e) and -|A| in pre-training (its CQL agent's rule)
        assert cfg.offline.cql.num_critics == cfg.online.sac.num_critics == 10
        assert cfg.offline.cql.cql_penalty_critics == 2 and cfg.online.sac.target_entropy == -adim
        assert cfg.offline.cql.target_entropy is None  # -> -|A| when the agent is created
        assert cfg.online.offline_ratio == 0.0 and cfg.online.utd == 4
        # antmaze's actor has a state-independent std (WSRL), pre-training and fine-tuning alike
        assert not cfg.offline.cql.state_dependent_std and not cfg.online.sac.state_dependent_std
    assert resolve(make_preset("door-binary-v0", "full", "wsrl")).online.sac.state_dependent_std
    boto_iql = resolve(make_preset(base, "quick", "boto", "iql"))
    # IQL pre-trains the networks the SAC learner takes over: the paper's, LayerNorm included
    iql = boto_iql.offline.iql
    assert boto_iql.online.sac.critic_hidden_dims == iql.critic_hidden_dims
    assert boto_iql.online.sac.state_dependent_std == iql.state_dependent_std
    assert iql.critic_layer_norm and iql.num_critics == boto_iql.online.sac.num_critics == 4


def test_dict_round_trip():
    cfg = resolve(make_preset("kitchen-mixed-v0", "full", "boto", "cql"))
    back = from_dict(RunConfig, to_dict(cfg))
    assert back == cfg


def test_dotted_overrides_and_shortcuts():
    cfg = build_config(["--task", "pointmaze-umaze", "--online.steps", "7000", "--offline.cql.cql_weight", "2.5",
                        "--network.critic_hidden_dims", "64", "64", "--alpha", "0.3", "--demos", "/x/demos.npz"])
    assert cfg.online.steps == 7000 and cfg.offline.cql.cql_weight == 2.5
    assert cfg.online.sac.critic_hidden_dims == (64, 64) == cfg.offline.cql.critic_hidden_dims
    assert cfg.alpha == 0.3 and cfg.data.demos == "/x/demos.npz"
    bare = build_config([])
    assert (bare.task, bare.method, bare.profile, bare.pretrain) == ("pointmaze-umaze", "boto", "quick", "calql")
    assert bare.offline.steps == QUICK_POINTMAZE_PRETRAIN


def test_run_config_file(tmp_path, capsys):
    """`botorl run --config FILE` (what a sweep's trial runs): the config to_dict wrote, with the
    run's own --out, --pretrained and --no-progress; anything else, or a file that is not such a
    config, is exit 2 naming it."""
    import json

    from botorl.configs.build import make_config

    cfg = make_config({"online.steps": "70"}, task="pointmaze-umaze", method="wsrl", seeds="0-1", profile="smoke")
    path = tmp_path / "cfg.json"
    path.write_text(json.dumps(to_dict(cfg)))
    back = build_config(["--config", str(path), "--out", "d", "--pretrained", "p", "--no-progress"])
    assert back == from_dict(RunConfig, {**to_dict(cfg), "out": "d", "pretrained": "p", "progress": False})
    assert back.seeds == "0-1" and back.online.steps == 70
    assert build_config([f"--config={path}"]) == cfg
    code, err = _run(capsys, tmp_path, "--config", str(path), "--seed", "3", "--online.steps=9")
    assert code == 2 and "--seed, --online.steps cannot go with it" in err, err
    for text in ("{not json", json.dumps({"task": "pointmaze-umaze"}), json.dumps({**to_dict(cfg), "extra": 1}),
                 json.dumps({**to_dict(cfg), "seed": "zero"})):
        path.write_text(text)
        with pytest.raises(ConfigError, match="cannot be read as a run config"):
            build_config(["--config", str(path)])
    path.write_text(json.dumps({**to_dict(cfg), "online": {**to_dict(cfg.online), "steps": -5}}))
    with pytest.raises(ConfigError, match="--online.steps = -5"):  # validated again
        build_config(["--config", str(path)])
    with pytest.raises(ConfigError, match="cannot be read"):
        build_config(["--config", str(tmp_path / "missing.json")])


@pytest.mark.parametrize("section, field, value", [
    ("online.sac", "critic_hidden_dims", [10**9]),  # would pass the bounds on network.* and exhaust memory
    ("offline.iql", "value_hidden_dims", [8]),
    ("offline.cql", "num_critics", 3),
    ("offline.cql", "calql", False),  # pretrain says calql
])
def test_a_config_file_whose_agent_copy_differs_is_refused(tmp_path, capsys, section, field, value):
    """A derived field is never taken from a file (`--config`, a run's config.json): one whose
    agent's copy differs from the run-config field it copies is exit 2 naming both, before any
    work, and in seconds (the critic-width case built a 10**9-unit layer before)."""
    import json
    import time

    from botorl.configs.resolve import DERIVED
    from botorl.pipeline.policy import read_run

    doc = to_dict(resolve(make_preset("pointmaze-umaze", "smoke", "boto")))
    outer, inner = section.split(".")
    doc[outer][inner][field] = value
    path = tmp_path / "cfg.json"
    path.write_text(json.dumps(doc))
    start = time.monotonic()
    code, err = _run(capsys, tmp_path, "--config", str(path))
    assert code == 2 and time.monotonic() - start < 30
    assert f"{section}.{field} = " in err and DERIVED[field] in err and "Traceback" not in err, err
    run = tmp_path / "r"
    run.mkdir()
    (run / "config.json").write_text(json.dumps(doc))
    with pytest.raises(ConfigError, match=f"{section}.{field} = .* differs from {DERIVED[field]}"):
        read_run(run)


def test_a_config_file_from_before_the_utd_left_the_agents_still_runs(tmp_path):
    """A file written when the agents' configs held a copy of the UTD (``utd_ratio``) reads back
    as the same config: the UTD is online.utd's, and the run keeps its identity (so resumes)."""
    import json

    from botorl.configs.schema import run_identity

    cfg = resolve(make_preset("pointmaze-umaze", "smoke", "calql"))
    doc = to_dict(cfg)
    doc["online"]["sac"]["utd_ratio"], doc["offline"]["cql"]["utd_ratio"] = cfg.online.utd, 1
    (tmp_path / "old.json").write_text(json.dumps(doc))
    assert build_config(["--config", str(tmp_path / "old.json")]) == cfg
    # the digests of this very config before the field left the schema (commit 8a7021f)
    assert (run_identity(cfg)["config"], run_identity(cfg)["pretraining"]) == ("442f01618c14703c", "6ca13608f9b565d7")


def test_quick_pointmaze_pretrain_default_and_budget():
    # The paper's pipeline on every profile: BOTO and WSRL pre-train with Cal-QL; on quick
    # pointmaze with 2 action samples per kind, 128-row batches and one budget for every
    # pre-training algorithm; other domains keep 5 samples, 256 rows and 10k steps.
    for method in ("boto", "wsrl"):
        cfg = build_config(["--method", method])
        assert cfg.pretrain == "calql" and cfg.offline.cql.calql
        assert cfg.offline.steps == QUICK_POINTMAZE_PRETRAIN
        assert (cfg.offline.cql.cql_n_actions, cfg.offline.batch_size) == (2, 128)
    assert build_config(["--pretrain", "iql"]).offline.steps == QUICK_POINTMAZE_PRETRAIN
    assert build_config(["--method", "iql"]).offline.steps == QUICK_POINTMAZE_PRETRAIN
    assert build_config(["--method", "cql"]).offline.steps == QUICK_POINTMAZE_PRETRAIN
    door = build_config(["--task", "door-binary-local"])
    assert door.pretrain == "calql" and door.offline.steps == 10_000
    assert (door.offline.cql.cql_n_actions, door.offline.batch_size) == (5, 256)
    assert build_config(["--profile", "full"]).pretrain == "calql"


def test_mid_profile_is_quick_with_the_10_critic_ensemble_and_longer_boto():
    # one size up from quick: only the ensemble (pre-training and fine-tuning) and the BOTO
    # stage grow, so a quick result and its mid re-run differ in those alone
    for method in ("boto", "wsrl", "calql"):
        quick, mid = (resolve(make_preset("pointmaze-medium", p, method)) for p in ("quick", "mid"))
        critics = 2 if method == "calql" else 10
        assert mid.offline.cql.num_critics == mid.online.sac.num_critics == critics
        assert mid.boto.boto_steps == 10_000 and quick.boto.boto_steps == 5_000
        # with the ensemble and BOTO stage set back, mid is quick field for field
        back = replace(mid, profile="quick", network=quick.network, boto=quick.boto,
                       offline=replace(mid.offline, cql=quick.offline.cql, iql=quick.offline.iql),
                       online=replace(mid.online, sac=quick.online.sac))
        assert back == quick


# ----------------------------------------------------------------------------- errors
def _run(capsys, tmp_path, *args):
    out = tmp_path / "run"
    code = botorl_main(["run", "--out", str(out), *args])
    err = capsys.readouterr().err
    assert not out.exists(), "a bad configuration must fail before the run directory is made"
    return code, err


@pytest.mark.parametrize(
    "args, needles",
    [
        (["--task", "pointmaze-largee"], ["unknown task 'pointmaze-largee'", "pointmaze-large"]),
        (["--method", "botox"], ["unknown method 'botox'", "boto, wsrl, calql, cql, iql, rlpd"]),
        (["--alpha", "1.5"], ["alpha = 1.5 is outside [-1, 1]", "--alpha -0.5"]),
        (["--alpha", "-2"], ["outside [-1, 1]"]),
        (["--online.steps", "-5"], ["--online.steps = -5", "non-negative"]),
        (["--offline.steps", "-1"], ["--offline.steps = -1"]),
        (["--boto.boto_steps", "-10"], ["--boto.boto_steps = -10"]),
        (["--warmup.steps", "-3"], ["--warmup.steps = -3"]),
        (["--profile", "huge"], ["unknown profile 'huge'"]),
        (["--method", "wsrl", "--alpha", "0.5"], ["--method wsrl has no BOTO phase"]),
        (["--method", "cql", "--pretrain", "iql"], ["--method cql pre-trains with cql"]),
        (["--pretrain", "bc"], ["unknown pre-training algorithm 'bc'"]),
        (["--eval.interval", "0"], ["--eval.interval = 0", "positive"]),
        (["--warmup.steps", "50"], ["--online.steps = 40 leaves no fine-tuning after the 50-step warm-up"]),
        (["--seed", "1", "--seeds", "0-1"], ["--seed and --seeds are both given", "(e.g. --seeds 0-7)"]),
        (["--alpha", "0.5", "--alphas", "-1,1"], ["--alpha and --alphas are both given", "(e.g. --alphas -1:1:0.25)"]),
        (["--online.offline_ratio", "2"], ["--online.offline_ratio = 2.0 is invalid: must lie in [0, 1]."]),
        (["--online.buffer_capacity", "0"], ["--online.buffer_capacity = 0 is invalid: must be positive or None."]),
        (["--boto.batch_size", str(2**21)], ["--boto.batch_size = 2097152 is invalid: a batch size must be an integer"]),
    ],
)
def test_bad_configuration_exit_2(capsys, tmp_path, args, needles):
    code, err = _run(capsys, tmp_path, "--profile", "smoke", *args) if "--profile" not in args else _run(capsys, tmp_path, *args)
    assert code == 2, err
    for n in needles:
        assert n in err, err


def test_missing_dataset_exit_2(capsys, tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "empty-minari"))
    code, err = _run(capsys, tmp_path, "--task", "antmaze-large-diverse-v2", "--profile", "smoke")
    assert code == 2 and "minari download D4RL/antmaze/large-diverse-v1" in err, err
    code, err = _run(capsys, tmp_path, "--task", "door-binary-v0", "--profile", "smoke")
    assert code == 2 and "Cal-QL" in err, err
    code, err = _run(capsys, tmp_path, "--task", "door-binary-v0", "--profile", "smoke",
                     "--data.path", str(tmp_path / "nowhere"))
    assert code == 2 and "nowhere" in err, err


def test_missing_door_demos_exit_2(capsys, tmp_path, monkeypatch):
    monkeypatch.delenv("BOTORL_DOOR_DEMOS", raising=False)
    # an empty dataset cache: a door dataset another test generated needs no demos, and the run would go on
    monkeypatch.setenv("BOTORL_DATA_DIR", str(tmp_path / "datasets"))
    code, err = _run(capsys, tmp_path, "--task", "door-binary-local", "--profile", "smoke",
                     "--demos", str(tmp_path / "no-demos.npz"))
    assert code == 2 and "no-demos.npz" in err and "door_human_demos.npz" in err, err
    from botorl.data.generators import door

    monkeypatch.setattr(door, "SHIPPED_DEMOS", tmp_path / "not-installed.npz")  # an install without the asset
    code, err = _run(capsys, tmp_path, "--task", "door-binary-local", "--profile", "smoke")
    assert code == 2 and "BOTORL_DOOR_DEMOS" in err, err


def test_resume_and_eval_of_a_non_run(capsys, tmp_path):
    assert botorl_main(["resume", str(tmp_path)]) == 2
    assert "not a botorl run directory" in capsys.readouterr().err
    assert botorl_main(["eval", str(tmp_path)]) == 2
    assert "not a botorl run directory" in capsys.readouterr().err


def test_existing_out_is_refused(capsys, tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "config.json").write_text("{}")
    assert botorl_main(["run", "--profile", "smoke", "--task", "pointmaze-umaze", "--out", str(out)]) == 2
    assert "botorl resume" in capsys.readouterr().err


def test_online_mc_returns_follow_the_offline_rule():
    """Cal-QL continued online: MC returns of finished episodes, same rule as the data."""
    from types import SimpleNamespace

    import numpy as np

    from botorl.data.replay import ReplayBuffer
    from botorl.pipeline.runner import with_mc_returns

    cfg = resolve(make_preset("pointmaze-umaze", "smoke", "calql"))
    spec = get_task(cfg.task)
    ctx = SimpleNamespace(mc_returns=lambda ds: with_mc_returns(cfg, spec, ds).mc_returns)
    buf = ReplayBuffer(10, 1, 1)
    for r, done in [(-5.0, False), (-5.0, False), (5.0, True), (-5.0, False), (-5.0, False)]:
        buf.insert(np.zeros(1), np.zeros(1), r, np.zeros(1), done)
    buf.set_mc_returns([0, 1, 2], ctx.mc_returns)  # reaches the goal
    buf.set_mc_returns([3, 4], ctx.mc_returns)  # truncated, never succeeds: r_neg / (1 - gamma)
    g2 = 5.0
    g1 = -5.0 + 0.99 * g2
    g0 = -5.0 + 0.99 * g1
    np.testing.assert_allclose(buf.mc_returns[:5], [g0, g1, g2, -500.0, -500.0], rtol=1e-5)


def test_bare_botorl_trains_nothing_and_says_what_there_is(capsys, tmp_path, monkeypatch):
    from botorl.cli import main as botorl_main

    monkeypatch.chdir(tmp_path)
    assert botorl_main([]) == 0
    out = capsys.readouterr().out
    assert "usage: botorl <command>" in out and "botorl run" in out and "python3 -m pytest -q" in out
    assert not any(tmp_path.iterdir()), "a bare `botorl` must not start a run (no run directory)"


def test_run_help_names_the_population_flags(capsys):
    from botorl.cli import main as botorl_main

    with pytest.raises(SystemExit) as exit_info:
        botorl_main(["run", "--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert "--seeds" in out and "--alphas" in out and "--pretrained" in out


# ------------------------------------------------------------------ one fact, one field
@pytest.mark.parametrize("flag, names", [
    (["--online.sac.utd-ratio", "8"], "--online.utd"),
    (["--offline.cql.num_critics", "3"], "--network.num-critics"),
    (["--offline.iql.value-hidden-dims", "8"], "--network.critic-hidden-dims"),
    (["--online.sac.no-critic-layer-norm"], "--network.layer-norm"),
    (["--offline.cql.calql=False"], "--pretrain"),
])
def test_a_derived_agent_field_is_refused_naming_its_one_flag(capsys, flag, names):
    # --online.steps 0 fails validation too: a code that took the flag would not start a run here
    assert botorl_main(["run", "--profile", "smoke", "--online.steps", "0", *flag]) == 2
    err = capsys.readouterr().err
    assert flag[0].split("=")[0] in err and f"give {names} instead" in err


def test_each_agent_takes_network_from_the_one_field_and_no_utd():
    from botorl.configs.resolve import DERIVED

    cfg = build_config(["--method", "calql", "--profile", "smoke", "--online.utd", "3", "--network.num-critics", "5",
                        "--network.critic-hidden-dims", "8", "8", "--network.no-layer-norm"])
    for agent in (cfg.offline.cql, cfg.offline.iql, cfg.online.sac):
        assert agent.num_critics == 5 and agent.critic_hidden_dims == (8, 8) and not agent.critic_layer_norm
    assert cfg.offline.iql.value_hidden_dims == (8, 8)
    # the UTD is online.utd alone: an update's batch carries it as its minibatches
    # (test_calql_pretrains_on_one_batch_per_critic_step), so no agent config holds a copy
    assert not [f for a in (cfg.offline.cql, cfg.offline.iql, cfg.online.sac) for f in vars(a) if "utd" in f]
    assert set(DERIVED) <= {f for a in (cfg.offline.cql, cfg.offline.iql) for f in vars(a)}


def test_seeds_and_alphas_are_config_fields():
    from botorl.configs.members import is_population, population

    cfg = build_config(["--profile", "smoke", "--seeds", "3-4", "--alphas", "-1:1:1"])  # '-1:...' after a space
    assert (cfg.seeds, cfg.alphas, cfg.seed, cfg.alpha) == ("3-4", "-1:1:1", 3, -1.0) and is_population(cfg)
    members, cfgs = population(cfg)
    assert [(m.seed, m.alpha) for m in members] == [(s, a) for a in (-1.0, 0.0, 1.0) for s in (3, 4)]
    assert [(c.seed, c.alpha, c.seeds, c.alphas) for c in cfgs[:2]] == [(3, -1.0, None, None), (4, -1.0, None, None)]
    assert from_dict(RunConfig, to_dict(cfg)) == cfg
    assert not is_population(build_config(["--profile", "smoke"]))


def _help_options(text: str) -> list[tuple[str, str]]:
    """(flag line, help text) of every option in a tyro help screen (box borders stripped)."""
    out, cur = [], None
    for line in (re.sub(r"^[│\s]+|[│\s]+$", "", raw) for raw in text.splitlines()):
        if re.fullmatch(r"[-─]{3,}", line):  # a section's rule
            continue
        if line.startswith("-"):
            cur = [line, ""]
            out.append(cur)
        elif cur is not None and line and not line.startswith(("╭", "╰", "─")):
            cur[1] += " " + line
        elif not line:
            cur = None
    return [tuple(o) for o in out]


def help_artefacts(text: str) -> list[str]:
    """What a help screen must not show: tyro's doubled negation, numbers split at their commas
    by the wrapper, files users do not have (the docs' .md sources), and a "(default: X)" tyro
    appends to a help text that already says what the default is."""
    flat = " ".join(re.sub(r"^[│\s]+|[│\s]+$", "", line) for line in text.splitlines())
    bad = ["--no-no-"] if "no-no-" in flat else []
    bad += re.findall(r"\b\d{1,3}, \d{3}\b", flat)
    bad += re.findall(r"[\w./-]+\.md\b", flat)
    for flag, text_ in _help_options(text):
        body = f"{flag} {text_}".strip()
        hint = re.search(r"\(default: [^)]*\)$", body)
        if hint and re.search(r"default", body[:hint.start()], re.I):
            bad.append(f"two defaults for {flag.split()[0]}")
    return bad


def test_help_artefacts_are_found():
    """The checker can fail: each artefact the issue reported, as tyro printed it."""
    assert help_artefacts("│ --progress, --no-no-progress │") == ["--no-no-"]
    assert help_artefacts("│ --x INT  steps (paper: 1, 000,000) (default: 1) │") == ["1, 000"]
    assert help_artefacts("│ --out STR  run directory; default runs/x. (default: None) │") == ["two defaults for --out"]
    assert help_artefacts("│ --net  sizes (algorithms.md). │") == ["algorithms.md"]
    assert help_artefacts("│ --seed INT  the seed (default: 0) │") == []


@pytest.mark.parametrize("command", ["run", "resume", "eval", "export", "sweep", "report"])
def test_help_is_one_style_without_tyro_artefacts(command, capsys, monkeypatch):
    from botorl.cli import main as botorl_main

    monkeypatch.setenv("COLUMNS", "100")
    with pytest.raises(SystemExit) as exit_info:
        botorl_main([command, "--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: botorl {command} ")
    # tyro's layout for every command (resume and eval were plain argparse): boxes on a
    # terminal, a ruled section header otherwise
    assert re.search(r"╭─ options|^ options *\n -{10,}", out, re.M), out[:2000]
    assert help_artefacts(out) == []


ALL_TASKS = PAPER_TASKS + GENERATED


@pytest.mark.parametrize("profile", PROFILES)
def test_wsrl_settings_in_every_method_and_profile(profile):
    # issue 40: the three settings checked against WSRL's code (docs/methods.md, "WSRL's settings,
    # checked"), read from the resolved config of every method, task and profile
    for task in ALL_TASKS:
        adim = get_task(task).action_dim
        for method in METHODS:
            cfg = resolve(make_preset(task, profile, method))
            sac, cql = cfg.online.sac, cfg.offline.cql
            # fine-tuning's target entropy: -|A| for WSRL's SAC (boto, wsrl), RLPD's own -|A|/2;
            # the continued baselines and pre-training keep their agent's rule (None -> -|A|)
            want = {"boto": -adim, "wsrl": -adim, "rlpd": -adim / 2}.get(method)
            assert sac.target_entropy == want, (task, method)
            assert cql.target_entropy is None


def test_lagrange_penalty_is_the_multiplier_alone():
    # WSRL's CQL: lambda * mean(diff - gap), no cql_weight factor (the hand computation of the
    # whole loss is test_agents_losses.py::test_cql_penalty_with_importance_sampling)
    import jax.numpy as jnp

    from botorl.agents.cql import CQLAgent

    cfg = resolve(make_preset("antmaze-large-diverse-v2", "full", "boto")).offline.cql
    assert cfg.cql_lagrange and cfg.cql_weight == 5.0
    small = replace(cfg, actor_hidden_dims=(8,), critic_hidden_dims=(8,), num_critics=2, cql_penalty_critics=None,
                    num_min_critics=2)
    agent = CQLAgent.create(small, 3, 2, seed=0)
    assert float(agent._penalty_weight()) == pytest.approx(float(agent.lagrange_value()))
    diff = jnp.asarray([1.8, 1.8])
    want = -float(agent.lagrange_value()) * (1.8 - cfg.cql_target_action_gap)
    assert float(agent.lagrange_loss(agent.lagrange.params, diff)) == pytest.approx(want, rel=1e-6)


def test_calql_pretrains_on_one_batch_per_critic_step(tmp_path, monkeypatch):
    # `--method calql --online.utd 4`: every pre-training critic step sees the whole offline
    # batch (24 rows here), and fine-tuning's update splits its 4 x 12 rows into 4 critic
    # minibatches of 12. Shapes are recorded while the critic step is traced (rows no other
    # test uses, so no cached compilation skips the trace).
    from botorl.agents.cql import CQLAgent

    seen = []
    step = CQLAgent.critic_step

    def recording(self, batch, key):
        seen.append(int(batch["rewards"].shape[-1]))
        return step(self, batch, key)

    monkeypatch.setattr(CQLAgent, "critic_step", recording)
    out = tmp_path / "run"
    # 340 online steps: Cal-QL waits for the first finished episode (300 steps) before updating
    rc = botorl_main(["run", "--method", "calql", "--profile", "smoke", "--online.utd", "4", "--online.steps", "340",
                      "--offline.batch-size", "24", "--online.batch-size", "12", "--out", str(out)])
    assert rc == 0
    assert seen and set(seen) == {24, 12}, seen
    assert seen[0] == 24  # pre-training's trace comes first


def test_print_config_prints_the_resolved_config_and_writes_nothing(capsys, tmp_path, monkeypatch):
    import json

    from botorl.envs.registry import get_task as task

    monkeypatch.chdir(tmp_path)
    assert botorl_main(["run", "--method", "wsrl", "--print-config"]) == 0
    cfg = json.loads(capsys.readouterr().out)
    assert cfg["method"] == "wsrl" and cfg["online"]["sac"]["target_entropy"] == -task(cfg["task"]).action_dim
    assert list(tmp_path.iterdir()) == []

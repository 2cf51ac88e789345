"""A method owns its facts (botorl/configs/methods.py): its name (one ``Literal``, the type of
``RunConfig.method``), fine-tuning's target entropy, and the refusal of an alpha it has no
BOTO phase for."""

from __future__ import annotations

import ast
import typing
from pathlib import Path

import pytest

from botorl.configs.methods import METHODS, PRETRAIN_ALGOS, MethodName, PretrainName, get_method
from botorl.configs.schema import RunConfig
from botorl.errors import ConfigError

CONFIGS = Path(__file__).resolve().parents[1] / "botorl" / "configs"


def test_the_names_are_one_literal():
    assert tuple(METHODS) == typing.get_args(MethodName) and all(m.name == k for k, m in METHODS.items())
    assert PRETRAIN_ALGOS == typing.get_args(PretrainName)
    hints = typing.get_type_hints(RunConfig)
    assert hints["method"] == MethodName and hints["pretrain"] == typing.Optional[PretrainName]


def test_an_alpha_without_boto_is_refused_by_the_method():
    with pytest.raises(ConfigError, match="--alphas sets BOTO's bias controller; --method rlpd has no BOTO phase"):
        get_method("rlpd").refuse_alpha("--alphas")
    get_method("boto").refuse_alpha("--alpha")  # boto takes one


def test_the_target_entropy_is_set_in_one_place():
    # the method's number, set by resolve alone (presets.py and resolve.py each set RLPD's before)
    assert {k: m.target_entropy_per_dim for k, m in METHODS.items() if m.target_entropy_per_dim is not None} == {
        "boto": -1.0, "wsrl": -1.0, "rlpd": -0.5}
    sets = [(p.name, n.lineno) for p in sorted(CONFIGS.glob("*.py")) for n in ast.walk(ast.parse(p.read_text()))
            if isinstance(n, ast.keyword) and n.arg == "target_entropy"]
    assert [name for name, _ in sets] == ["resolve.py"], sets


def test_a_runs_alpha_is_checked_once_where_it_enters(monkeypatch):
    """The run's config: validate refuses an alpha for a method without BOTO and checks its
    range, once; the population's members and the BOTO stage (boto_updates) take it as checked."""
    import numpy as np

    from botorl.agents.population import stack
    from botorl.agents.sac import SACAgent, SACConfig
    from botorl.boto import phase
    from botorl.configs import members, resolve
    from botorl.configs.methods import Method
    from botorl.data.dataset import Dataset
    from botorl.pipeline.cli import build_config

    calls = []
    for module in (resolve, members, phase):
        monkeypatch.setattr(module, "check_alpha", lambda a, *_, m=module.__name__: calls.append((m, a)))
    monkeypatch.setattr(Method, "refuse_alpha", lambda self, flag: calls.append(("refuse", flag)))
    cfg = build_config(["--profile", "smoke", "--seeds", "0-1", "--alphas", "-0.5,0.5"])
    _, member_cfgs = members.population(cfg)
    agent = SACAgent.create(SACConfig(actor_hidden_dims=(8,), critic_hidden_dims=(8,), num_critics=2), 3, 2, 0)
    data = Dataset(np.zeros((10, 3)), np.zeros((10, 2)), np.zeros(10), np.zeros((10, 3)), np.zeros(10))
    phase.boto_updates(stack([agent] * 4), data, [None] * 4, cfg.boto, [c.alpha for c in member_cfgs], [0, 1, 0, 1])
    assert calls == [("refuse", "--alpha"), ("botorl.configs.resolve", -0.5)]


def test_the_boto_stage_checks_alpha_once(monkeypatch):
    # train_boto checks its alphas on entry, not again at every call's population update
    import numpy as np

    from botorl.agents.population import stack
    from botorl.agents.sac import SACAgent, SACConfig
    from botorl.boto import objective, phase
    from botorl.data.dataset import Dataset

    calls, check = [], objective.check_alpha
    monkeypatch.setattr(phase, "check_alpha", lambda a: calls.append(a) or check(a))
    monkeypatch.setattr(objective, "check_alpha", lambda a: calls.append(a))
    agent = SACAgent.create(SACConfig(actor_hidden_dims=(8,), critic_hidden_dims=(8,), num_critics=2), 3, 2, 0)
    data = Dataset(np.zeros((10, 3)), np.zeros((10, 2)), np.zeros(10), np.zeros((10, 3)), np.zeros(10))
    config = phase.BOTOConfig(boto_steps=2, steps_per_call=1, batch_size=4)
    phase.train_boto(stack([agent, agent]), data, [None, None], config, [0.5, -0.5], [0, 1], progress=False)
    assert len(calls) == 1
    with pytest.raises(ConfigError, match=r"alpha = \[0.5, -3.0\] is outside \[-1, 1\]"):
        phase.train_boto(stack([agent, agent]), data, [None, None], config, [0.5, -3.0], [0, 1], progress=False)

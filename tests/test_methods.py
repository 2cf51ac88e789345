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

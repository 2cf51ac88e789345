"""The manipulation check reads the two evaluations around the BOTO stage from eval.csv."""

from __future__ import annotations

import math

import pytest

from botorl.experiments.manipulation import MANIPULATION_KEYS, q_around_boto

# as a run with a 30-step warm-up and evaluations every 20 steps writes it: the warm-up's
# evaluation at 0, repeated at 20 (the frozen policy), fine-tuning's first at 30 (after BOTO)
EVAL = """stage,env_step,success,return,q_data,q_uniform
warmup,0,0.5,1,0.35,0.33
warmup,20,0.5,1,0.35,0.33
finetune,30,0,0,0.30,0.28
finetune,40,1,2,0.9,0.1
"""


def test_before_is_the_warmups_step_0_after_is_finetunings_first(tmp_path):
    (tmp_path / "eval.csv").write_text(EVAL)
    got = q_around_boto(tmp_path)
    assert list(got) == list(MANIPULATION_KEYS)
    assert got["q_data_before"] == 0.35 and got["q_uniform_before"] == 0.33
    assert got["q_data_after"] == 0.30 and got["q_uniform_after"] == 0.28
    assert got["q_data_change"] == pytest.approx(-0.05) and got["q_uniform_change"] == pytest.approx(-0.05)
    assert q_around_boto(tmp_path / "eval.csv") == got  # the file itself


def test_what_the_file_does_not_hold_is_nan(tmp_path):
    assert all(math.isnan(v) for v in q_around_boto(tmp_path).values())  # no eval.csv
    # no warm-up: fine-tuning evaluates at 0 after BOTO, nothing before it; a line cut by a kill
    (tmp_path / "eval.csv").write_text("stage,env_step,success,return,q_data,q_uniform\nfinetune,0,0,0,0.2,0.1\n"
                                       "finetune,10,0,0,0.3,")
    got = q_around_boto(tmp_path)
    assert got["q_data_after"] == 0.2 and got["q_uniform_after"] == 0.1
    assert all(math.isnan(got[k]) for k in MANIPULATION_KEYS if not k.endswith("after"))
    # an eval.csv from before the Q columns
    (tmp_path / "eval.csv").write_text("stage,env_step,success,return\nwarmup,0,1,1\nfinetune,5,1,1\n")
    assert all(math.isnan(v) for v in q_around_boto(tmp_path).values())

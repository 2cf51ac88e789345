"""The manipulation check of a BOTO-stage study: did the stage move Q, and at which actions?

A run's ``eval.csv`` already holds what it takes (pipeline/runner.py, ``RunContext.evaluate``):
every evaluation logs the critic ensemble's mean Q on a fixed probe of dataset pairs
(``q_data``) and on the same states with uniform actions (``q_uniform``), the same probe for
every run of a task (``Streams.PROBE``), in the critic's reward-transformed units. Two of its
rows bracket the BOTO stage (pipeline/stages.py):

- **before**: the warm-up's evaluation at env step 0 (stage ``warmup``). The warm-up trains
  nothing, so this is the pre-trained critic, the same for every arm that starts from one
  pre-training (its later ``warmup`` rows repeat it).
- **after**: fine-tuning's first evaluation (stage ``finetune``, at env step ``warmup.steps``),
  made before its first update. Its critic is the one the BOTO stage left (a warm start copies
  the critics whole, ``SACAgent.from_pretrained``); for a method without a BOTO stage (WSRL) it
  is still the pre-trained one, so its change is 0 and the arm is the check's baseline.

A run without a warm-up (``warmup.steps`` 0) logs no evaluation before the BOTO stage: its
"before" values are nan.
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from botorl.experiments.runs import to_float
from botorl.io import CSV_LIMIT, read_bounded

# the keys of what q_around_boto returns, in the order a table shows them
MANIPULATION_KEYS = ("q_data_before", "q_data_after", "q_data_change",
                     "q_uniform_before", "q_uniform_after", "q_uniform_change")


def q_around_boto(run: Path) -> dict[str, float]:
    """Q on dataset and on uniform actions just before and just after the BOTO stage, from the
    ``eval.csv`` of ``run`` (a run directory or a study's folder of a run's records; a path to
    the file itself also works). Returns ``{key: float}`` for every key of MANIPULATION_KEYS:
    ``q_data_before`` / ``q_uniform_before`` (the pre-trained critic: the warm-up's evaluation
    at env step 0), ``q_data_after`` / ``q_uniform_after`` (fine-tuning's first evaluation:
    the critic the BOTO stage left), and ``*_change`` = after - before. A value the file does not
    hold (no such row, no Q columns, no eval.csv, a line cut by a kill) is nan. A file that is
    not a regular file of bounded size raises as ``botorl.io.read_bounded`` does."""
    path = Path(run)
    path = path / "eval.csv" if path.is_dir() else path
    out = dict.fromkeys(MANIPULATION_KEYS, math.nan)
    if not path.exists():
        return out
    before = after = None
    with io.StringIO(read_bounded(path, CSV_LIMIT), newline="") as f:
        for row in csv.DictReader(f):
            stage = row.get("stage")
            if before is None and stage == "warmup" and to_float(row.get("env_step")) == 0:
                before = row
            elif after is None and stage == "finetune":
                after = row
    for q in ("q_data", "q_uniform"):
        out[f"{q}_before"], out[f"{q}_after"] = to_float((before or {}).get(q)), to_float((after or {}).get(q))
        out[f"{q}_change"] = out[f"{q}_after"] - out[f"{q}_before"]
    return out

"""One seed plan: every random stream of a run comes from ``configs.members.Streams``.

The numbers are pinned (runs made before the plan existed must stay the same), and no library
module derives a stream of its own: arithmetic on a seed, a ``[seed, k]`` SeedSequence, or one
of the plan's constants used in a sum or product, outside ``botorl/configs/members.py``.
"""

from __future__ import annotations

import ast
from pathlib import Path
from types import SimpleNamespace

from botorl.configs.members import Streams

ROOT = Path(__file__).resolve().parents[1] / "botorl"
# Programs with seeds of their own, which are no run's streams: the bandit figures, the ant
# expert's trainer, the data generators, the benchmarks.
OWN_SEEDS = ("boto/bandit.py", "experts/", "data/generators/", "benchmarks/")
CONSTANTS = {1000, 7919, 1_000_003, 10_000, 100_000, 200_000, 12345}


def _seedy(node: ast.AST) -> bool:
    return "seed" in ast.unparse(node).lower()


def _int(node: ast.AST) -> bool:
    return isinstance(node, ast.Constant) and type(node.value) is int


def derivations(tree: ast.AST) -> list[str]:
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.BinOp) and isinstance(node.op, (ast.Add, ast.Mult)):
            sides = (node.left, node.right)
            if any(map(_int, sides)) and (any(map(_seedy, sides)) or any(_int(s) and s.value in CONSTANTS for s in sides)):
                out.append(ast.unparse(node))
        elif isinstance(node, (ast.List, ast.Tuple)) and len(node.elts) == 2 and any(map(_int, node.elts)) \
                and any(map(_seedy, node.elts)):
            out.append(ast.unparse(node))
    return out


def test_the_streams_are_todays():
    s = Streams.of(SimpleNamespace(seed=3, online_seed=5))
    assert (s.pretrain, s.pretrain_batches, s.pretrain_keys) == (3, [3, 1], 3 * 1_000_003 + 1)
    # warmup_env (o * 1000 + 7) is gone by design: the warm-up is the online loop's first steps
    assert (s.boto, s.scratch, s.warm_start) == (5, 5, 5 * 7919 + 3)
    assert (s.online_env, s.online_batches, s.evaluation, s.eval_command) == (5011, [5, 3], 103_000, 200_003)
    assert (Streams.PROBE, Streams.EVAL_ENVS) == (12345, 10_000)


def test_the_rule_finds_a_derivation():
    src = "a = mc.cfg.online_seed * 1000 + 7\nb = rng([cfg.seed, 3])\nc = make(seed=10_000 + i)\nd = n + 1\n"
    assert derivations(ast.parse(src)) == ["mc.cfg.online_seed * 1000 + 7", "mc.cfg.online_seed * 1000",
                                           "[cfg.seed, 3]", "10000 + i"]


def test_no_module_derives_a_stream_of_its_own():
    found = {}
    for p in sorted(ROOT.rglob("*.py")):
        rel = p.relative_to(ROOT).as_posix()
        if rel != "configs/members.py" and not rel.startswith(OWN_SEEDS) and (d := derivations(ast.parse(p.read_text()))):
            found[rel] = d
    assert not found, f"random streams derived outside configs.members.Streams (take them from there): {found}"

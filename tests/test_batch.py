"""One definition of the batch's keys: ``botorl.batch.Batch``; no module lists them again.

A tuple, list or set literal of four or more strings (or a dict literal with four or more such
keys), all of them batch keys and one of them ``"dones"``, is a second definition (as ``_FIELDS``, ``_KEYS`` and ``_BATCH_KEYS`` were); it
should take ``BATCH_KEYS`` or ``TRANSITION_KEYS`` from ``botorl.batch`` instead. ``"dones"`` is
the batch's own word: a Dataset and the files it is read from say ``terminals``, so their
field lists (``("observations", "actions", "rewards", "next_observations")``) are not batches.
"""

from __future__ import annotations

import ast
from pathlib import Path

from botorl.batch import BATCH_KEYS, TRANSITION_KEYS, Batch

ROOT = Path(__file__).resolve().parents[1] / "botorl"


def key_lists(tree: ast.AST) -> list[int]:
    """Lines of the literals that list batch keys."""
    lists = [(n.lineno, n.elts) for n in ast.walk(tree) if isinstance(n, (ast.Tuple, ast.List, ast.Set))]
    lists += [(n.lineno, n.keys) for n in ast.walk(tree) if isinstance(n, ast.Dict)]
    return [line for line, elts in lists if len(elts) >= 4 and any(getattr(e, "value", None) == "dones" for e in elts)
            and all(isinstance(e, ast.Constant) and e.value in BATCH_KEYS for e in elts)]


def test_the_keys_are_the_contracts():
    assert BATCH_KEYS == ("observations", "actions", "rewards", "next_observations", "dones", "mc_returns")
    assert TRANSITION_KEYS == BATCH_KEYS[:5] and tuple(Batch.__annotations__) == BATCH_KEYS


def test_the_rule_finds_a_second_definition():
    assert key_lists(ast.parse('_KEYS = ("observations", "actions", "rewards", "next_observations", "dones")')) == [1]
    assert key_lists(ast.parse('[x for x in ["observations", "dones", "rewards", "actions", "mc_returns"]]')) == [1]
    assert key_lists(ast.parse('fields = ("observations", "actions", "rewards", "next_observations")')) == []
    assert key_lists(ast.parse('b = {"observations": o, "actions": a, "rewards": r, "dones": d}')) == [1]
    assert key_lists(ast.parse('tails = {"observations": 1, "actions": 2, "next_observations": 3, **x}')) == []


def test_no_module_lists_the_batch_keys_again():
    found = {str(p.relative_to(ROOT.parent)): lines for p in sorted(ROOT.rglob("*.py"))
             if (lines := key_lists(ast.parse(p.read_text())))}
    assert not found, f"batch keys listed outside botorl/batch.py (take them from botorl.batch): {found}"

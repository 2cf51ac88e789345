"""One definition of the batch's keys: ``botorl.batch.Batch``; no module lists them again.

A tuple, list or set literal of four or more strings, all of them batch keys and one of them
``"dones"``, is a second definition (as ``_FIELDS``, ``_KEYS`` and ``_BATCH_KEYS`` were); it
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
    return [node.lineno for node in ast.walk(tree) if isinstance(node, (ast.Tuple, ast.List, ast.Set))
            and len(node.elts) >= 4 and all(isinstance(e, ast.Constant) and e.value in BATCH_KEYS for e in node.elts)
            and any(e.value == "dones" for e in node.elts)]


def test_the_keys_are_the_contracts():
    assert BATCH_KEYS == ("observations", "actions", "rewards", "next_observations", "dones", "mc_returns")
    assert TRANSITION_KEYS == BATCH_KEYS[:5] and tuple(Batch.__annotations__) == BATCH_KEYS


def test_the_rule_finds_a_second_definition():
    assert key_lists(ast.parse('_KEYS = ("observations", "actions", "rewards", "next_observations", "dones")')) == [1]
    assert key_lists(ast.parse('[x for x in ["observations", "dones", "rewards", "actions", "mc_returns"]]')) == [1]
    assert key_lists(ast.parse('fields = ("observations", "actions", "rewards", "next_observations")')) == []


def test_no_module_lists_the_batch_keys_again():
    found = {str(p.relative_to(ROOT.parent)): lines for p in sorted(ROOT.rglob("*.py"))
             if (lines := key_lists(ast.parse(p.read_text())))}
    assert not found, f"batch keys listed outside botorl/batch.py (take them from botorl.batch): {found}"

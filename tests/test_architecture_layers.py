"""The import rule of docs/architecture.md: at module level a package imports only packages of
its own layer or below. Function-level imports are free (they keep `botorl --help` fast and
break cycles); the page lists the two that reach up a layer."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PKG = REPO / "botorl"

# docs/architecture.md, "Layers: what may import what"
LAYER = {
    "errors": 0, "io": 0, "jaxsetup": 0, "__init__": 0,
    "networks": 1,
    "agents": 2,
    "envs": 3, "data": 3,
    "boto": 4,
    "configs": 5,
    "pipeline": 6,
    "experiments": 7,
    "cli": 8, "bench": 8, "benchmarks": 8,
}


def _part(module: str) -> str:
    """`botorl.agents.sac` -> `agents`; `botorl` -> `__init__`."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _module_level_imports(tree: ast.Module):
    """Imports that run when the module is imported: the module body, and the bodies of
    top-level `if`/`try` blocks (not functions or classes)."""
    todo = list(tree.body)
    while todo:
        node = todo.pop()
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.module
        elif isinstance(node, (ast.If, ast.Try)):
            todo += node.body + node.orelse + getattr(node, "finalbody", [])
            todo += [s for h in getattr(node, "handlers", []) for s in h.body]


def test_every_package_has_a_layer():
    parts = {p.stem if p.is_file() else p.name for p in PKG.iterdir()
             if (p.suffix == ".py") or (p.is_dir() and (p / "__init__.py").exists())}
    assert parts <= set(LAYER), f"give {sorted(parts - set(LAYER))} a layer here and in docs/architecture.md"


def test_module_level_imports_go_down_the_layers():
    bad = []
    files = sorted(PKG.rglob("*.py"))
    assert len(files) > 50  # the whole package is scanned
    for path in files:
        rel = path.relative_to(REPO).with_suffix("")
        src = _part(".".join(rel.parts))
        for target in _module_level_imports(ast.parse(path.read_text())):
            if target != "botorl" and not target.startswith("botorl."):
                continue
            dst = _part(target)
            if dst != src and LAYER[dst] > LAYER[src]:
                bad.append(f"{rel}.py imports {target} (layer {LAYER[dst]}) from layer {LAYER[src]}")
    assert not bad, "module-level imports that reach up a layer (docs/architecture.md):\n" + "\n".join(bad)


# The function-level imports that reach up a layer, each for one pure table or function
# (docs/architecture.md names both); a new one should move the shared piece down instead.
UPWARD_INSIDE_FUNCTIONS = {("agents", "data"), ("configs", "pipeline")}


def test_only_the_listed_function_level_imports_reach_up():
    found = set()
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(REPO).with_suffix("")
        src = _part(".".join(rel.parts))
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module] if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module
                     else [])
            for target in names:
                if target.startswith("botorl.") and LAYER[_part(target)] > LAYER[src] and _part(target) != src:
                    found.add((src, _part(target)))
    assert found == UPWARD_INSIDE_FUNCTIONS, (
        f"upward imports {sorted(found)}; docs/architecture.md lists {sorted(UPWARD_INSIDE_FUNCTIONS)}")

"""The import graph of botorl: no circle, no upward arrow, no private name taken from another module.

Every ``import`` / ``from ... import`` of a botorl module is read from the source (``ast``),
those inside functions included. The packages are layers, each importing only from its own
layer and the ones below:

    errors, io, jaxsetup, batch  <  networks  <  agents  <  envs  <  data  <  experts  <  boto
      <  configs  <  pipeline  <  experiments, benchmarks

Command modules (``botorl/cli.py`` and every ``<package>/cli.py`` or ``*_cli.py``: what
``botorl <command>`` runs) and the Python front door ``botorl/api.py`` (``botorl.run`` etc.,
which calls the command functions) sit above all of them; no library module imports one.

Imports are at module level: one inside a function carries its reason (``# lazy: ...``), and
there are at most ``MAX_LAZY`` of them (issue 43).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "botorl"
LAYERS = [("errors", "io", "jaxsetup", "batch", "__init__"), ("networks",), ("agents",), ("envs",), ("data",), ("experts",),
          ("boto",), ("configs",), ("pipeline",), ("experiments", "benchmarks")]
LAYER = {pkg: i for i, pkgs in enumerate(LAYERS) for pkg in pkgs}


def _modules() -> dict[str, Path]:
    out = {}
    for p in ROOT.rglob("*.py"):
        parts = p.relative_to(ROOT.parent).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return out


MODULES = _modules()


def _imports(name: str, path: Path) -> list[tuple[str, list[str], int]]:
    """(imported botorl module, names taken from it, line) for every import in the file."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [(a.name, [], node.lineno) for a in node.names if a.name.split(".")[0] == "botorl"]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1] + [base]).rstrip(".")
            if base.split(".")[0] != "botorl":
                continue
            for a in node.names:  # `from botorl.x import y` imports module botorl.x.y when there is one
                sub = f"{base}.{a.name}"
                out.append((sub, [], node.lineno) if sub in MODULES else (base, [a.name], node.lineno))
    return out


GRAPH = {name: _imports(name, path) for name, path in MODULES.items()}


def _layer(module: str) -> int:
    parts = module.split(".")
    return LAYER[parts[1] if len(parts) > 1 else "__init__"]


def _is_command(module: str) -> bool:
    last = module.rpartition(".")[2]
    return last == "cli" or last.endswith("_cli") or module == "botorl.api"


def test_every_package_has_a_layer():
    assert {m.split(".")[1] for m in MODULES if m.count(".") >= 1 and not _is_command(m)} - {
        p.removesuffix(".py") for p in LAYER} <= {"cli"}


def test_no_import_circle():
    edges = {m: {t for t, _, _ in imps if t in MODULES and t != m} for m, imps in GRAPH.items()}
    state: dict[str, int] = {}
    path: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        path.append(m)
        for t in sorted(edges[m]):
            if state.get(t) == 1:
                raise AssertionError("import circle: " + " -> ".join(path[path.index(t):] + [t]))
            if t not in state:
                visit(t)
        path.pop()
        state[m] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m)


def test_no_upward_arrow():
    bad = []
    for m, imps in GRAPH.items():
        for t, _, line in imps:
            if t not in MODULES and t.rpartition(".")[0] in MODULES:
                t = t.rpartition(".")[0]
            if t not in MODULES or _is_command(m):
                continue
            if _is_command(t) or _layer(t) > _layer(m):
                bad.append(f"{MODULES[m].relative_to(ROOT.parent)}:{line} imports {t}")
    assert not bad, "imports against the layers:\n" + "\n".join(bad)


def test_no_private_name_from_another_module():
    bad = []
    for m, imps in GRAPH.items():
        for t, names, line in imps:
            bad += [f"{m}:{line} takes {t}.{n}" for n in names if n.startswith("_") and n != "__version__"]
        # `module._name` through a module imported whole (`from botorl.agents import common as C; C._update`)
        nodes = list(ast.walk(ast.parse(MODULES[m].read_text())))
        aliases = {}
        for node in nodes:
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("botorl"):
                aliases.update({a.asname or a.name: f"{node.module}.{a.name}" for a in node.names
                                if f"{node.module}.{a.name}" in MODULES})
            elif isinstance(node, ast.Import):
                aliases.update({a.asname: a.name for a in node.names if a.name.startswith("botorl") and a.asname})
        bad += [f"{m}:{node.lineno} takes {aliases[node.value.id]}.{node.attr}" for node in nodes
                if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases
                and node.attr.startswith("_") and not node.attr.startswith("__")]
    assert not bad, "private names used across modules:\n" + "\n".join(bad)


# ------------------------------------------------------------------ issue 43: imports at module level
# An import inside a function says why on its line or just above it, with a "# lazy:" comment
# (one comment may head a block of imports): an optional extra, JAX kept out of what botorl.api
# imports, a module the spawned workers import, an import order a library needs. Everything
# else is imported at module level.
MAX_LAZY = 60


def _lazy_imports(path: Path) -> list[tuple[int, bool]]:
    """(line, has its reason) of every import statement inside a function of ``path``."""
    lines = path.read_text().splitlines()
    tree = ast.parse("\n".join(lines))
    imports = [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
    import_lines = {i for n in imports for i in range(n.lineno, n.end_lineno + 1)}
    inside = {id(n) for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
              for n in ast.walk(f) if isinstance(n, (ast.Import, ast.ImportFrom))}
    out = []
    for node in imports:
        if id(node) not in inside:
            continue
        # its own lines, then up through the block of imports (and blank lines) it belongs to
        # and the comment line that heads it
        seen = list(range(node.lineno, node.end_lineno + 1))
        i = node.lineno - 1
        while i >= 1 and (i in import_lines or not lines[i - 1].strip()):
            seen.append(i)
            i -= 1
        if i >= 1 and lines[i - 1].lstrip().startswith("#"):
            seen.append(i)
        out.append((node.lineno, any("# lazy:" in lines[j - 1] for j in seen)))
    return out


def test_imports_inside_functions_are_few_and_say_why():
    found = {p: _lazy_imports(p) for p in sorted(ROOT.rglob("*.py"))}
    total = sum(len(v) for v in found.values())
    rel = {p: str(p.relative_to(ROOT.parent)) for p in found}
    missing = [f"{rel[p]}:{line}" for p, v in found.items() for line, ok in v if not ok]
    assert not missing, ("imports inside a function without a `# lazy: <reason>` comment (move them to "
                         "module level, or say why not):\n" + "\n".join(missing))
    assert total <= MAX_LAZY, (f"{total} imports inside functions, more than {MAX_LAZY}:\n" + "\n".join(
        f"{rel[p]}: {len(v)}" for p, v in sorted(found.items(), key=lambda kv: -len(kv[1])) if v))

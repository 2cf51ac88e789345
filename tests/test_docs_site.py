"""The documentation: the MkDocs site builds with --strict (a broken link or anchor, a page
missing from the navigation, or a docstring mkdocstrings cannot render fails it), the README
stays a front door, and nothing committed under docs/ names a path of the machine it was
written on."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
README = REPO / "README.md"

# Absolute paths of a machine (a home, a scratch or a work directory); `~/.botorl` and
# relative paths are fine.
MACHINE_PATH = re.compile(r"(?<![\w.~])/(?:work|root|tmp|home)/")

TWO_COMMANDS = """```bash
pip install -e . && botorl run                      # install; a whole BOTO run on pointmaze-umaze (data made here; ~3-4 min on 2 cores)
pip install -e ".[test]" && python3 -m pytest -q    # install the test dependencies; run the tests
```"""


@pytest.fixture(scope="module")
def built_site(tmp_path_factory) -> Path:
    for module in ("mkdocs", "material", "mkdocstrings"):
        if importlib.util.find_spec(module) is None:
            pytest.fail(f"{module} is not installed: the docs tools are in the test extra, "
                        f'`pip install -e ".[test]"` (or ".[docs]")')
    site = tmp_path_factory.mktemp("site")
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")  # Material's banner about MkDocs 2.0
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(site)],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, f"mkdocs build --strict failed (exit {proc.returncode}):\n{proc.stderr}\n{proc.stdout}"
    return site


def test_mkdocs_build_strict(built_site):
    # the pages of the navigation and the API reference rendered from the docstrings
    for page in ("index.html", "getting-started/index.html", "results/index.html", "performance/index.html",
                 "architecture/index.html", "contributing/index.html", "results/pointmaze-medium/report/index.html"):
        assert (built_site / page).is_file(), page
    api = (built_site / "reference" / "boto" / "index.html").read_text()
    assert "boto_update_many" in api and "hybrid_noise" in api
    assert "SACAgent" in (built_site / "reference" / "agents" / "index.html").read_text()
    # the figures the result pages embed are copied with them
    assert (built_site / "results" / "study" / "dip.png").is_file()


def test_readme_is_a_front_door():
    text = README.read_text()
    lines = text.splitlines()
    assert len(lines) <= 300, f"README.md has {len(lines)} lines; depth goes into docs/ (at most 300 here)"
    assert lines[0] == "# botorl"
    # the two commands right after the title and the one-line description
    assert text.index(TWO_COMMANDS) < text.index("\n## "), "the two commands come first"
    assert "\n## Results\n" in text
    # every relative link of the README points at a file of the repository
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
        if "://" not in target:
            assert (REPO / target).exists(), f"README.md links to {target}, which does not exist"


def test_no_machine_paths_in_docs():
    files = [p for p in DOCS.rglob("*") if p.is_file()] + [README, REPO / "mkdocs.yml"]
    assert len(files) > 50
    found = []
    for path in files:
        try:
            text = path.read_text()
        except UnicodeDecodeError:  # figures
            continue
        for n, line in enumerate(text.splitlines(), 1):
            if MACHINE_PATH.search(line):
                found.append(f"{path.relative_to(REPO)}:{n}: {line.strip()[:120]}")
    assert not found, "absolute paths of a machine (write them relative to the report or the run):\n" + "\n".join(found)


def test_machine_path_pattern():
    # the check above can fail: what it must catch and what it must let through
    assert MACHINE_PATH.search("48 finished runs from /work/study/door")
    assert MACHINE_PATH.search("door,boto,0,/tmp/x/seed0")
    assert MACHINE_PATH.search("see /home/user/runs")
    assert not MACHINE_PATH.search("`~/.botorl/datasets` and study/door/seed0")
    assert not MACHINE_PATH.search("docs/results/work/report.md")

"""Imports run one way: import-linter checks the contracts of pyproject.toml on the tree as
a wheel lays it out (the source folders are mapped into one namespace, which the linter's
graph builder cannot follow in place)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
LINT_IMPORTS = "import sys; from importlinter.cli import lint_imports_command as c; sys.exit(c())"


@pytest.fixture(scope="module")
def installed_tree(tmp_path_factory) -> Path:
    """monoloc installed (no dependencies) into a plain folder, as from the wheel."""
    target = tmp_path_factory.mktemp("tree")
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "-q",
            "--no-deps",
            "--no-build-isolation",
            "--target",
            str(target),
            str(REPO),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    # The build leaves its scratch folder in the source tree.
    shutil.rmtree(REPO / "build", ignore_errors=True)
    return target


def _lint(tree: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    return subprocess.run(
        [
            sys.executable,
            "-c",
            LINT_IMPORTS,
            "--config",
            str(REPO / "pyproject.toml"),
            "--no-cache",
        ],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def test_the_import_contracts_hold(installed_tree):
    done = _lint(installed_tree)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
    assert "0 broken" in done.stdout


def test_the_contracts_catch_a_client_module_importing_the_server(installed_tree, tmp_path):
    tree = tmp_path / "tree"
    shutil.copytree(installed_tree, tree)
    (tree / "monoloc" / "client" / "_leak.py").write_text("import monoloc.server.localize\n")
    done = _lint(tree)
    assert done.returncode != 0
    assert "monoloc.client._leak -> monoloc.server.localize" in done.stdout


def test_the_contracts_catch_an_import_cycle_hidden_in_a_function(installed_tree, tmp_path):
    tree = tmp_path / "tree"
    shutil.copytree(installed_tree, tree)
    core = tree / "monoloc" / "core"
    (core / "_a.py").write_text("def f():\n    from monoloc.core import _b\n    return _b\n")
    (core / "_b.py").write_text("from monoloc.core import _a\n")
    done = _lint(tree)
    assert done.returncode != 0
    assert "No cycles are allowed in monoloc.core" in done.stdout

"""The distribution maps the top-level folders to one ``monoloc`` namespace: every package
folder of the tree is listed in pyproject.toml, under the name it is imported by."""

from __future__ import annotations

import importlib
import subprocess
import sys
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def _setuptools_config() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]


def _package_folders(config: dict) -> dict[str, Path]:
    """Every folder holding an ``__init__.py`` under a mapped folder, by package name."""
    found: dict[str, Path] = {}
    for name, folder in config["package-dir"].items():
        root = REPO / folder
        for init in root.rglob("__init__.py"):
            rel = init.parent.relative_to(root)
            found[".".join([name, *rel.parts])] = init.parent
    return found


def test_every_package_folder_is_listed_under_its_namespace_name():
    config = _setuptools_config()
    folders = _package_folders(config)
    # A folder nested in a mapped folder that is itself mapped appears once per mapping.
    assert set(config["packages"]) == set(folders)
    assert {"monoloc.server", "monoloc.client", "monoloc.sim", "monoloc.core"} <= set(folders)
    assert "monoloc.migrations.versions" in folders
    assert "script.py.mako" in config["package-data"]["monoloc.migrations"]


def test_each_listed_package_imports_from_its_folder():
    config = _setuptools_config()
    for name, folder in _package_folders(config).items():
        if name.startswith("monoloc.migrations"):
            continue  # env.py runs only inside alembic
        module = importlib.import_module(name)
        assert Path(module.__file__).parent == folder, name


def test_a_users_own_server_module_does_not_shadow_monoloc(tmp_path):
    # The first wave's packages were called server/client/sim: a user's server.py broke them.
    (tmp_path / "server.py").write_text("RAISE = 1\n")
    (tmp_path / "client.py").write_text("RAISE = 1\n")
    code = "import monoloc.server.localize, monoloc.client.api, server; print(server.RAISE)"
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, check=False
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "1"

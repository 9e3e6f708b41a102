"""The vehicle library must stay light: importing all of `monoloc.client` and
`monoloc.core` pulls in no heavy deps."""

import json
import subprocess
import sys

FORBIDDEN = (
    "cv2",
    "faiss",
    "fastapi",
    "starlette",
    "uvicorn",
    "sqlalchemy",
    "alembic",
    "pydantic",
    "pydantic_settings",
    "skimage",
    "numba",
    "matplotlib",
)

_PROBE = """
import importlib, json, pkgutil, sys
import monoloc.client
import monoloc.core
names = ["monoloc.client", "monoloc.core"]
for package in (monoloc.client, monoloc.core):
    for info in pkgutil.walk_packages(package.__path__, prefix=package.__name__ + "."):
        importlib.import_module(info.name)
        names.append(info.name)
heavy = sorted(m for m in sys.modules if m.split(".")[0] in {forbidden})
print(json.dumps({{"modules": names, "heavy": heavy}}))
"""


def test_importing_every_client_module_loads_no_heavy_dependency():
    code = _PROBE.format(forbidden=set(FORBIDDEN))
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert "monoloc.core.geometry" in report["modules"]
    assert report["heavy"] == [], f"client imports heavy modules: {report['heavy']}"


def test_the_probe_would_notice_a_heavy_import():
    # Guard against a probe that can never fail: importing cv2 next to client is caught.
    code = "import cv2\n" + _PROBE.format(forbidden=set(FORBIDDEN))
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )
    assert "cv2" in json.loads(done.stdout.strip().splitlines()[-1])["heavy"]

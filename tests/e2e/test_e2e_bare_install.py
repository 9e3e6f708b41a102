"""A bare ``pip install monoloc`` is the vehicle library: built as a wheel, installed in a
fresh virtual environment without extras, it drives a run against a live server of the
full install, and names the extra a server command needs instead of a traceback."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import venv
from pathlib import Path

import pytest
from e2e_helpers import QUERY_SEQ, printed_rmse_m, query_drive_args

REPO = Path(__file__).resolve().parents[2]
HEAVY = ("cv2", "faiss", "fastapi", "sqlalchemy", "numba", "skimage", "matplotlib")


def _run(args: list[str], timeout: float = 600, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(
        args, capture_output=True, text=True, timeout=timeout, check=False, **kwargs
    )


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """monoloc built as a wheel from this checkout."""
    root = tmp_path_factory.mktemp("wheel")
    built = _run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "-q",
            "--no-deps",
            "--no-build-isolation",
            "-w",
            str(root),
            str(REPO),
        ]
    )
    shutil.rmtree(REPO / "build", ignore_errors=True)
    assert built.returncode == 0, built.stderr[-2000:]
    (path,) = root.glob("monoloc-*.whl")
    return path


def _fresh_venv(root: Path, requirement: str) -> Path:
    venv.create(root / "venv", with_pip=True)
    python = root / "venv" / "bin" / "python"
    installed = _run([str(python), "-m", "pip", "install", "-q", requirement])
    assert installed.returncode == 0, installed.stderr[-2000:]
    return root / "venv"


@pytest.fixture(scope="module")
def bare_venv(wheel, tmp_path_factory) -> Path:
    """A fresh venv holding the monoloc wheel and only its required dependencies."""
    return _fresh_venv(tmp_path_factory.mktemp("bare"), str(wheel))


@pytest.fixture(scope="module")
def bags_venv(wheel, tmp_path_factory) -> Path:
    """A fresh venv holding the monoloc wheel with the vehicle's ``[bags]`` extra."""
    return _fresh_venv(tmp_path_factory.mktemp("bags"), f"{wheel}[bags]")


def test_the_bare_install_holds_no_heavy_dependency(bare_venv):
    probe = (
        "import importlib.util, json; "
        f"print(json.dumps([m for m in {HEAVY!r} if importlib.util.find_spec(m)]))"
    )
    done = _run([str(bare_venv / "bin" / "python"), "-c", probe])
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == []


def test_the_bare_install_converts_a_track_to_wgs84(bare_venv):
    # pymap3d is a base dependency: the vehicle writes its GeoJSON track without extras
    probe = (
        "import json; from monoloc.core.geo import GeoOrigin, GeoReference; "
        "from monoloc.core.geometry import T_world_from_cam_planar; "
        "ref = GeoReference.from_origin(GeoOrigin(52.5, 13.4, 40.0, 90.0)); "
        "print(json.dumps(ref.geopose(T_world_from_cam_planar(0.0, 0.0, 0.0, 1.5)).to_json()))"
    )
    done = _run([str(bare_venv / "bin" / "python"), "-c", probe])
    assert done.returncode == 0, done.stderr
    position = json.loads(done.stdout)["position"]
    assert abs(position["lat"] - 52.5) < 1e-9 and abs(position["lon"] - 13.4) < 1e-9
    assert abs(position["h"] - 41.5) < 1e-6


def test_a_server_command_names_the_extra_it_needs(bare_venv, tmp_path):
    done = _run([str(bare_venv / "bin" / "monoloc"), "serve"], cwd=tmp_path)
    assert done.returncode == 1
    assert "Traceback" not in done.stderr
    assert "pip install 'monoloc[server]'" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1


def test_driving_a_bag_names_the_bags_extra(bare_venv, tmp_path):
    bag = tmp_path / "drive_bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    args = [str(bare_venv / "bin" / "monoloc"), "drive", str(bag), "--map", "m", "--key", "k"]
    done = _run(args, cwd=tmp_path)
    assert done.returncode == 1
    assert "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines() == [
        "error: reading ROS bags needs the 'rosbags' package: pip install 'monoloc[bags]'"
    ]


def test_the_bare_install_drives_a_run_against_a_full_server(bare_venv, live_map, tmp_path):
    out = tmp_path / "traj" / "query"
    env = dict(os.environ, COLUMNS="160", MONOLOC_API_KEY=live_map.keys.localize)
    drive_args = query_drive_args(live_map, out, key=False)
    args = [str(bare_venv / "bin" / "monoloc"), "drive", *drive_args]
    done = _run(args, cwd=tmp_path, env=env)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    tum = out.with_name("query.tum.txt")
    rows = [line.split() for line in tum.read_text().splitlines() if line.strip()]
    assert len(rows) >= 16 and all(len(r) == 8 for r in rows)
    assert printed_rmse_m(done.stdout) < 0.5


def test_the_bags_extra_drives_a_bag_without_the_server(bags_venv, live_map, tmp_path):
    # the vehicle replays a ROS 2 bag (CompressedImage, Odometry of base_link, the rig on
    # /tf_static) with the light install plus rosbags and Pillow: nothing of the server
    from rosbag_helpers import SimRun, write_sim_bag

    run = SimRun.read(live_map.dataset, QUERY_SEQ)
    bag = write_sim_bag(run, tmp_path / "query_bag", image="compressed", three_d="none")
    probe = (
        "import importlib.util, json; "
        f"print(json.dumps([m for m in {HEAVY!r} if importlib.util.find_spec(m)]))"
    )
    done = _run([str(bags_venv / "bin" / "python"), "-c", probe])
    assert done.returncode == 0 and json.loads(done.stdout) == [], done.stdout + done.stderr
    out = tmp_path / "traj" / "bag"
    env = dict(os.environ, COLUMNS="160", MONOLOC_API_KEY=live_map.keys.localize)
    args = [str(bags_venv / "bin" / "monoloc"), "drive", str(bag), "--server", live_map.url]
    args += ["--map", live_map.map_name, "--frames", "10:30", "--particles", "500"]
    args += ["--topic", "odometry=/odom", "--topic", "truth=/odom"]  # the sim's true motion
    done = _run([*args, "--out", str(out)], cwd=tmp_path, env=env)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert printed_rmse_m(done.stdout) < 0.5

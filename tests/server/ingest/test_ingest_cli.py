"""`monoloc map ...` and `monoloc localize` end to end on the hand-made sequence."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from monoloc.core.geometry import kitti_to_zup


@pytest.fixture(scope="module")
def app():
    from monoloc import cli

    cli._register()
    return cli.app


def _ok(app, *args, env):
    result = CliRunner().invoke(app, list(args), env=env, catch_exceptions=False)
    assert result.exit_code == 0, result.output
    return result.output


def test_map_commands(app, kitti_root, tmp_path):
    env = {"MONOLOC_DATA_DIR": str(tmp_path / "data")}
    seq_dir = kitti_root.sequence_dir
    out = _ok(app, "map", "create", "wall", "--camera", str(seq_dir / "calib.txt"), env=env)
    assert "created map wall (id 1)" in out and "width_px=620" in out
    out = _ok(
        app,
        "map",
        "ingest",
        "--map",
        "wall",
        str(kitti_root.root),
        "--frames",
        "0:5",
        "--tags",
        "day",
        env=env,
    )
    assert "entries added" in out and "5 of 5" in out
    out = _ok(app, "map", "ingest", "--map", "1", str(seq_dir), "--kind", "night", env=env)
    assert "already_in_map" in out and "8 of 8" in out
    out = _ok(app, "map", "stats", "wall", env=env)
    assert "entries" in out and "night: 3" in out and "day: 5" in out
    assert "not calibrated" in out
    assert "ORB corners" in out and "(the default)" in out
    listed = _ok(app, "map", "list", env=env)
    assert "wall" in listed and "grid" in listed and "upload the runs again" not in listed

    # One more reference image: frame 3 shifted (another file), LiDAR + calib.txt, --pose.
    import cv2

    image = cv2.imread(str(seq_dir / "image_0" / "000003.png"), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(tmp_path / "extra.png"), np.roll(image, 2, axis=1))
    pose = ",".join(f"{v:.12g}" for v in kitti_to_zup(kitti_root.T_kitti_from_cam[3]).ravel())
    out = _ok(
        app,
        "map",
        "add-image",
        "--map",
        "wall",
        str(tmp_path / "extra.png"),
        "--pose",
        pose,
        "--lidar",
        str(seq_dir / "velodyne" / "000003.bin"),
        "--lidar-extrinsics",
        str(seq_dir / "calib.txt"),
        "--tags",
        "manual",
        env=env,
    )
    assert out.startswith("added entry 9")

    out = _ok(
        app,
        "localize",
        "--map",
        "wall",
        str(seq_dir / "image_0" / "000004.png"),
        "--json",
        "--k",
        "3",
        env=env,
    )
    result = json.loads(out[out.index("{") :])
    assert len(result["retrieved"]) == 3 and set(result["timings_ms"]) >= {"total", "pnp"}
    assert result["kernel_warm_up_ms"] > 0  # the kernels load before the timed query
    assert result["timings_are"].startswith("cold") and result["map_load_ms"] > 0
    assert "warm_timings_ms_p50" not in result
    best = max(result["hypotheses"], key=lambda h: h["n_inliers"])
    truth = kitti_to_zup(kitti_root.T_kitti_from_cam[4])
    assert np.linalg.norm(np.array(best["T_world_from_cam"])[:3, 3] - truth[:3, 3]) < 0.05
    table = _ok(
        app,
        "localize",
        "--map",
        "wall",
        str(seq_dir / "image_0" / "000004.png"),
        "--prior",
        "0,0,0.5",
        "--repeat",
        "2",
        env=env,
    )
    assert "hypotheses from" in table and "total" in table
    flat = " ".join(table.split())
    assert "first query (ms, cold)" in flat and "warm p50 of 2 repeats (ms)" in flat
    assert "no compilation in it" in flat

    out = _ok(
        app,
        "map",
        "vocab",
        "--map",
        "wall",
        "--train-from",
        str(kitti_root.root),
        "--max-images",
        "8",
        env=env,
    )
    assert "job 1 done" in out and "9 entries recomputed (8 from their images, 1 from stored" in out


def test_bad_input_is_one_line_and_exit_code_1(kitti_copy, tmp_path):
    poses = kitti_copy.root / "poses" / "00.txt"
    lines = poses.read_text().splitlines()
    lines[3] = lines[3].replace(lines[3].split()[5], "nan", 1)
    poses.write_text("\n".join(lines) + "\n")
    env = {**os.environ, "MONOLOC_DATA_DIR": str(tmp_path / "data")}
    script = "from monoloc.cli import main; main()"
    create = [sys.executable, "-c", script, "map", "create", "w", "--camera", "kitti"]
    assert subprocess.run(create, env=env, capture_output=True).returncode == 0
    ingest = [sys.executable, "-c", script, "map", "ingest", "--map", "w", str(kitti_copy.root)]
    done = subprocess.run(ingest, env=env, capture_output=True, text=True)
    assert done.returncode == 1
    assert done.stderr.strip().count("\n") == 0
    assert "poses/00.txt:4: pose contains NaN" in done.stderr


def test_a_vocabulary_trains_on_a_run_without_lidar(app, kitti_copy, tmp_path):
    """`map vocab --train-from` reads the run's images only: a KITTI run without
    velodyne/ (a stereo or camera-only fleet) trains a vocabulary; `map ingest` still
    refuses to map from it without depth."""
    import shutil

    shutil.rmtree(kitti_copy.sequence_dir / "velodyne")
    env = {"MONOLOC_DATA_DIR": str(tmp_path / "data")}
    calib = kitti_copy.sequence_dir / "calib.txt"
    _ok(app, "map", "create", "cams", "--camera", str(calib), env=env)
    out = _ok(app, "map", "vocab", "--map", "cams", "--train-from", str(kitti_copy.root), env=env)
    assert "job 1 done" in out and "now on vocabulary" in out
    runner = CliRunner()
    ingest = ["map", "ingest", "--map", "cams", str(kitti_copy.root)]
    result = runner.invoke(app, ingest, env=env)
    assert result.exit_code == 1 and "velodyne" in str(result.exception or result.output)
    result = runner.invoke(app, [*ingest, "--depth-from", "none"], env=env)
    assert result.exit_code == 2 and "needs depth" in result.output

"""Mapping from a stereo camera: a sim run with image_1 and P1 but no LiDAR scans is read,
validated and ingested with ``depth_from="stereo"``; bad stereo input is refused naming
the file, before anything is stored."""

from __future__ import annotations

import re
import shutil
import sys

import numpy as np
import pytest

from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.server.ingest.manage import ingest_source
from monoloc.server.ingest.sources import read_kitti_sequence
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage import runs as runs_repo
from monoloc.server.storage.db import session_scope


@pytest.fixture
def no_lidar(stereo_dataset, tmp_path):
    """A copy of the stereo run without its velodyne/ and depth/ folders (a fleet
    without LiDAR)."""
    root = tmp_path / "stereo_only"
    shutil.copytree(stereo_dataset, root)
    seq = root / "sequences" / "00"
    shutil.rmtree(seq / "velodyne")
    shutil.rmtree(seq / "depth")
    return root


def test_a_run_without_lidar_is_mapped_from_stereo(no_lidar, factory, make_map):
    with pytest.raises(InputFileError, match="velodyne"):
        read_kitti_sequence(no_lidar, "00")
    source = read_kitti_sequence(no_lidar, "00", depth_from="stereo")
    assert source.n_frames == 6 and source.stereo_baseline_m == pytest.approx(0.5371657)
    map_id = make_map(source.intrinsics)
    summary = ingest_source(factory, map_id, source)
    assert summary.entries_added == 6 and summary.frames_skipped == 0
    assert summary.points_min >= 100  # half-size frames: ~600 ORB keypoints, most with depth
    with session_scope(factory) as session:
        entries = entries_repo.get_entry_data(
            session, [e.id for e in entries_repo.list_entries(session, map_id)]
        )
        run = runs_repo.list_runs(session, map_id)[0]
    assert run.source_format == "kitti" and run.entries_added == 6
    for entry in entries:
        z = entry.points_cam[:, 2]
        assert np.all((z >= 2.5) & (z <= 40.0))
        u = source.intrinsics.fx * entry.points_cam[:, 0] / z + source.intrinsics.cx
        assert np.allclose(u, entry.keypoints_px[:, 0], atol=1e-2)


def test_stereo_entries_agree_with_the_lidar_entries(stereo_dataset):
    """The same frame's keypoints that get a depth from both sources get nearly the same
    one (the LiDAR's is the reference of the sim's exact geometry)."""
    from monoloc.server.entry_builder import BuildConfig, points_for
    from monoloc.server.vision.features import OrbConfig, extract_features

    lidar = read_kitti_sequence(stereo_dataset, "00")
    stereo = read_kitti_sequence(stereo_dataset, "00", depth_from="stereo")
    errors = []
    for lf, sf in zip(lidar.frames, stereo.frames, strict=True):
        a, b = lidar.load(lf), stereo.load(sf)
        assert np.array_equal(a.image_gray, b.image_gray)
        features = extract_features(a.image_gray, OrbConfig())
        p_lidar, h_lidar = points_for(features, a.source, lidar.intrinsics, BuildConfig())
        p_stereo, h_stereo = points_for(
            features, b.source, stereo.intrinsics, BuildConfig(), a.image_gray
        )
        both = h_lidar & h_stereo
        errors.append(np.abs(p_stereo[both, 2] / p_lidar[both, 2] - 1.0))
        assert h_stereo.sum() > 2 * h_lidar.sum()  # stereo is dense, the scan is not
    rel = np.concatenate(errors)
    assert len(rel) > 100
    assert np.median(rel) < 0.02 and np.percentile(rel, 80) < 0.05


def test_bad_stereo_input_is_refused_naming_the_file(no_lidar):
    seq = no_lidar / "sequences" / "00"
    (seq / "image_1" / "000003.png").unlink()
    with pytest.raises(InputFileError, match=r"image_1/000003\.png"):
        read_kitti_sequence(no_lidar, "00", depth_from="stereo")
    shutil.copy(seq / "image_1" / "000002.png", seq / "image_1" / "000003.png")
    calib = (seq / "calib.txt").read_text()
    (seq / "calib.txt").write_text(
        "".join(line + "\n" for line in calib.splitlines() if not line.startswith(("P1", "P2")))
    )
    # P2 gone too: P0, P3 with a gap is refused by the calib reader itself.
    with pytest.raises(InputFileError, match="without a gap"):
        read_kitti_sequence(no_lidar, "00", depth_from="stereo")
    (seq / "calib.txt").write_text(
        "".join(line + "\n" for line in calib.splitlines() if line.startswith(("P0", "Tr")))
    )
    with pytest.raises(InputFileError, match="no P1 line"):
        read_kitti_sequence(no_lidar, "00", depth_from="stereo")
    lines = calib.splitlines()
    p1 = [float(v) for v in lines[1].split()[1:]]
    p1[7] = 5.0  # a y translation: not a rectified pair
    lines[1] = "P1: " + " ".join(f"{v:.12e}" for v in p1)
    (seq / "calib.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputFileError, match="not a rectified stereo pair"):
        read_kitti_sequence(no_lidar, "00", depth_from="stereo")
    p1[7], p1[3] = 0.0, -p1[3]  # camera 1 on the left
    lines[1] = "P1: " + " ".join(f"{v:.12e}" for v in p1)
    (seq / "calib.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputFileError, match="to the right"):
        read_kitti_sequence(no_lidar, "00", depth_from="stereo")
    with pytest.raises(InvalidInputError, match="unknown depth source"):
        read_kitti_sequence(no_lidar, "00", depth_from="radar")


def test_cli_ingests_with_depth_from_stereo(no_lidar, tmp_path, monkeypatch, capsys):
    from typer.testing import CliRunner

    from monoloc import cli

    cli._register()
    env = {"MONOLOC_DATA_DIR": str(tmp_path / "data")}
    seq = no_lidar / "sequences" / "00"
    runner = CliRunner()
    made = runner.invoke(cli.app, ["map", "create", "s", "--camera", str(seq)], env=env)
    assert made.exit_code == 0, made.output
    args = ["map", "ingest", "--map", "s", str(no_lidar), "--frames", "0:3"]
    out = runner.invoke(cli.app, [*args, "--depth-from", "stereo"], env=env)
    assert out.exit_code == 0, out.output
    assert re.search(r"3 of 3", out.output) and "entries added" in out.output
    # Without --depth-from the scans are needed: one error line, non-zero exit.
    monkeypatch.setenv("MONOLOC_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setattr(sys, "argv", ["monoloc", *args])
    with pytest.raises(SystemExit) as exited:
        cli.main()
    err = capsys.readouterr().err
    assert exited.value.code != 0
    assert err.startswith("error: ") and "velodyne" in err and len(err.splitlines()) == 1
    monkeypatch.setattr(sys, "argv", ["monoloc", *args, "--depth-from", "sonar"])
    with pytest.raises(SystemExit) as exited:
        cli.main()
    err = capsys.readouterr().err
    assert exited.value.code != 0 and err.startswith("error: ") and "sonar" in err

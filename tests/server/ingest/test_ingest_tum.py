"""The TUM RGB-D reader (association, ground truth, intrinsics) and a TUM ingestion."""

from __future__ import annotations

import json

import numpy as np
import pytest

from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.formats.tum import associate, ground_truth_at
from monoloc.core.geometry import (
    kitti_to_zup,
    quaternion_xyzw_from_R,
    zup_to_kitti,
)
from monoloc.server.ingest.pipeline import ingest_run
from monoloc.server.ingest.sources import read_tum_run
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage.db import session_scope


def test_association_is_greedy_one_to_one_within_tolerance():
    rgb = np.array([0.000, 0.010, 0.100, 0.200])
    depth = np.array([0.008, 0.095, 0.5])
    # 0.010 is closer to 0.008 than 0.000 is; 0.100 pairs with 0.095; 0.200 has no partner.
    assert associate(rgb, depth, 0.02) == [(1, 0), (2, 1)]
    assert associate(rgb, depth, 0.001) == []


def test_ground_truth_is_interpolated_or_nearest():
    yaw90 = quaternion_xyzw_from_R(np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]))
    gt = np.array([[0.0, 0, 0, 0, 0, 0, 0, 1], [1.0, 1, 0, 0, *yaw90]])
    T = ground_truth_at(gt, 0.5, gt_max_gap_s=2.0)
    np.testing.assert_allclose(T[:3, 3], [0.5, 0, 0])
    c = np.cos(np.pi / 4)
    np.testing.assert_allclose(T[:2, :2], [[c, -c], [c, c]], atol=1e-9)
    assert ground_truth_at(gt, 0.5) is None  # samples 1 s apart: no interpolation
    np.testing.assert_allclose(ground_truth_at(gt, 1.015)[:3, 3], [1, 0, 0])  # nearest
    assert ground_truth_at(gt, 1.05) is None


def test_reads_a_tum_run(tum_run, kitti_root):
    run = read_tum_run(tum_run)
    assert run.intrinsics == kitti_root.camera and run.depth_scale_per_m == 5000
    assert [f.index for f in run.frames] == [1, 2, 3, 4, 5, 6]
    assert run.read_skips == {"no_depth": 1, "no_ground_truth": 1}
    frame = run.frames[2]
    assert frame.depth_timestamp_s == pytest.approx(frame.timestamp_s + 0.004)
    np.testing.assert_allclose(
        frame.T_world_from_cam, kitti_to_zup(kitti_root.T_kitti_from_cam[3]), atol=1e-6
    )
    loaded = run.load(frame)
    assert loaded.image_gray.ndim == 2 and loaded.source.depth_raw.dtype == np.uint16
    named = read_tum_run(tum_run, camera="freiburg1")
    assert named.intrinsics.fx == 517.3 and named.intrinsics.width_px == 640


def test_world_frame_option_converts_camera_style_worlds(tum_run):
    z_up = read_tum_run(tum_run).frames[0].T_world_from_cam
    meta = json.loads((tum_run / "intrinsics.json").read_text())
    (tum_run / "intrinsics.json").write_text(json.dumps({**meta, "world_frame": "kitti"}))
    converted = read_tum_run(tum_run).frames[0].T_world_from_cam
    np.testing.assert_allclose(converted, kitti_to_zup(z_up), atol=1e-9)
    np.testing.assert_allclose(zup_to_kitti(converted), z_up, atol=1e-9)


def test_bad_tum_inputs_name_file_and_line(tum_run):
    gt = tum_run / "groundtruth.txt"
    lines = gt.read_text().splitlines()
    gt.write_text("\n".join(lines[:3] + [lines[3].rsplit(" ", 1)[0] + " 7.0"] + lines[4:]))
    with pytest.raises(InputFileError, match=r"groundtruth\.txt:4: quaternion norm"):
        read_tum_run(tum_run)
    gt.write_text("\n".join(lines))
    (tum_run / "intrinsics.json").rename(tum_run / "elsewhere.json")
    with pytest.raises(InvalidInputError, match="no camera intrinsics"):
        read_tum_run(tum_run)
    assert read_tum_run(tum_run, camera="freiburg2").n_frames == 6
    (tum_run / "rgb" / "10.300000.png").unlink()
    with pytest.raises(InputFileError, match=r"rgb\.txt:5: lists rgb/10\.300000\.png"):
        read_tum_run(tum_run, camera="freiburg2")


def test_tum_ingestion_puts_points_on_the_wall(tum_run, kitti_root, factory, make_map, make_run):
    run = read_tum_run(tum_run)
    map_id = make_map(run.intrinsics)
    summary = ingest_run(factory, map_id, run, run_id=make_run(map_id, run))
    assert summary.entries_added == 6 and summary.frames_total == 8
    assert summary.skip_reasons == {"no_depth": 1, "no_ground_truth": 1}
    with session_scope(factory) as session:
        ids = [e.id for e in entries_repo.list_entries(session, map_id)]
        entries = entries_repo.get_entry_data(session, ids)
    for entry in entries:
        T = zup_to_kitti(entry.T_world_from_cam)
        z = entry.points_cam @ T[2, :3] + T[2, 3]
        assert len(z) > 300 and np.abs(z - kitti_root.wall_z_m).max() < 0.01


def test_tum_through_the_cli(tum_run, tmp_path):
    from typer.testing import CliRunner

    from monoloc import cli

    cli._register()
    env = {"MONOLOC_DATA_DIR": str(tmp_path / "data")}

    def ok(*args):
        result = CliRunner().invoke(cli.app, list(args), env=env, catch_exceptions=False)
        assert result.exit_code == 0, result.output
        return result.output

    assert "width_px=620" in ok("map", "create", "room", "--camera", str(tum_run))
    out = ok(
        "map", "ingest", "--map", "room", "--format", "tum", str(tum_run), "--kind", "offcenter"
    )
    assert "no_ground_truth" in out and "no_depth" in out and "8 of 8" in out
    assert "off-center: 6" in ok("map", "stats", "room")

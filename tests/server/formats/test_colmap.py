"""COLMAP models in and out: a SIFT + LiDAR model of a sim run imported both ways (ORB
features given the model's points by proximity, or the model's own observations),
localized against, exported, opened by pycolmap and imported again."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from cli_runner import run_monoloc
from colmap_builder import build_sift_model
from map_checks import query_position_errors_m

from monoloc.core.geometry import invert_rigid
from monoloc.server.formats.colmap import read_colmap_model
from monoloc.server.formats.maps import entry_name, export_map, import_sources_into_map
from monoloc.server.formats.model import import_sources
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage.db import session_scope


@pytest.fixture(scope="module")
def sift_model(map_run, tmp_path_factory):
    return build_sift_model(map_run, tmp_path_factory.mktemp("colmap"))


def _entries(factory, map_id):
    with session_scope(factory) as session:
        ids = [s.id for s in entries_repo.list_entries(session, map_id, limit=1000)]
        return entries_repo.get_entry_data(session, ids)


def _import(factory, name, model, points, up=None):
    sources = import_sources(model, fmt="colmap", up=up, points=points)
    record, summaries, created = import_sources_into_map(factory, name, sources)
    assert created and len(summaries) == 1
    return record, summaries[0]


def _lidar_depths(map_run, frame_index, keypoints_px):
    from monoloc.server.vision.depth import points_from_lidar

    scan = map_run.load(map_run.frames[frame_index]).source
    points, has = points_from_lidar(
        keypoints_px, scan.points_lidar, scan.T_cam_from_lidar, map_run.intrinsics
    )
    return np.where(has, points[:, 2], np.nan)


@pytest.mark.parametrize("points", ["orb", "model"])
def test_import_gives_true_poses_and_lidar_consistent_points(factory, sift_model, map_run, points):
    model_dir, images_dir, truth = sift_model
    model = read_colmap_model(model_dir, images_dir)
    assert model.default_up == "-y"  # a foreign model: no monoloc.json
    record, summary = _import(factory, f"m-{points}", model, points)
    assert summary.entries_added == len(truth) == 8 and summary.frames_skipped == 0
    assert record.camera == map_run.intrinsics
    for entry, frame in zip(_entries(factory, record.id), map_run.frames, strict=True):
        # The model's KITTI-like world (-y up) came back to the z-up world.
        np.testing.assert_allclose(entry.T_world_from_cam, frame.T_world_from_cam, atol=1e-6)
        assert len(entry.points_cam) >= 20
        # Every 3D point reprojects onto its keypoint and has the depth the LiDAR gives
        # there (the model's points came from the LiDAR at the SIFT keypoints).
        K = map_run.intrinsics.K
        projected = entry.points_cam @ K.T
        np.testing.assert_allclose(
            projected[:, :2] / projected[:, 2:],
            entry.keypoints_px,
            atol=0.05 if points == "orb" else 2e-3,
        )
        lidar = _lidar_depths(map_run, frame.index, entry.keypoints_px)
        relative = np.abs(entry.points_cam[:, 2] - lidar) / lidar
        assert np.nanmedian(relative) < 0.02 and np.mean(np.isfinite(lidar)) > 0.5


def test_orb_mode_keypoints_are_orb_detections_model_mode_the_observations(
    factory, sift_model, map_run
):
    from monoloc.server.vision.features import extract_features

    model_dir, images_dir, _ = sift_model
    model = read_colmap_model(model_dir, images_dir)
    orb_map, _ = _import(factory, "orb", model, "orb")
    model_map, _ = _import(factory, "model", model, "model")
    first = map_run.load(map_run.frames[0]).image_gray
    detected = extract_features(first).keypoints_px
    orb_entry, model_entry = _entries(factory, orb_map.id)[0], _entries(factory, model_map.id)[0]
    assert all(np.any(np.all(detected == kp, axis=1)) for kp in orb_entry.keypoints_px)
    observed = model.images[0].keypoints_px
    distance = np.linalg.norm(model_entry.keypoints_px[:, None] - observed[None], axis=2)
    assert distance.min(axis=1).max() < 1e-4


def test_imported_map_localizes_a_query_frame(factory, settings, sift_model, query_run):
    from monoloc.server.map_registry import MapRegistry

    model_dir, images_dir, _ = sift_model
    model = read_colmap_model(model_dir, images_dir)
    record, _ = _import(factory, "loc", model, "orb")
    registry = MapRegistry(factory, settings.index_dir)
    errors = query_position_errors_m(registry, record.id, query_run)
    assert np.median(errors) < 0.3, errors


def test_export_opens_in_colmap_and_imports_back(factory, sift_model, tmp_path):
    """A map imported from a SIFT model, exported (its previews as the images, points
    merged into tracks) and imported again from the export alone."""
    import pycolmap

    from monoloc.server.formats.maps import TrackMerge

    model_dir, images_dir, _ = sift_model
    first, _ = _import(factory, "first", read_colmap_model(model_dir, images_dir), "model")
    record, n = export_map(factory, "first", "colmap", tmp_path / "export")
    assert n == 8
    reconstruction = pycolmap.Reconstruction(str(tmp_path / "export"))
    assert reconstruction.num_reg_images() == 8
    entries = _entries(factory, first.id)
    radius = TrackMerge().radius_m
    for entry in entries:
        image = reconstruction.find_image_with_name(entry_name(entry.id))
        T_cam_from_world = np.eye(4)
        T_cam_from_world[:3] = image.cam_from_world().matrix()
        np.testing.assert_allclose(
            invert_rigid(T_cam_from_world), entry.T_world_from_cam, atol=1e-9
        )
        xyz = np.array(
            [reconstruction.points3D[p.point3D_id].xyz for p in image.points2D if p.has_point3D()]
        )
        world = entry.points_cam @ entry.T_world_from_cam[:3, :3].T + entry.T_world_from_cam[:3, 3]
        assert np.linalg.norm(xyz - world, axis=1).max() <= radius + 1e-4
    model = read_colmap_model(tmp_path / "export", tmp_path / "export" / "images")
    assert model.default_up == "z"  # monoloc.json beside the export
    second, summary = _import(factory, "second", model, "model")
    assert summary.entries_added == 8
    for a, b in zip(entries, _entries(factory, second.id), strict=True):
        np.testing.assert_allclose(b.T_world_from_cam, a.T_world_from_cam, atol=1e-9)
        np.testing.assert_allclose(b.keypoints_px, a.keypoints_px, atol=1e-4)
        assert np.linalg.norm(b.points_cam - a.points_cam, axis=1).max() <= radius + 1e-4


def test_up_auto_matches_the_stated_axis_for_a_level_camera(sift_model):
    model_dir, images_dir, truth = sift_model
    model = read_colmap_model(model_dir, images_dir)
    stated = import_sources(model, fmt="colmap", up="-y")[0].frames
    auto = import_sources(model, fmt="colmap", up="auto")[0].frames
    for a, b in zip(stated, auto, strict=True):
        # The sim's camera is level up to its small pitch: auto's up is within 2 degrees.
        up_a, up_b = -a.T_world_from_cam[:3, 1], -b.T_world_from_cam[:3, 1]
        assert np.degrees(np.arccos(np.clip(up_a @ up_b, -1, 1))) < 2.0
    wrong = import_sources(model, fmt="colmap", up="z")[0].frames[0]
    assert abs(wrong.T_world_from_cam[2, 1]) < 0.5  # the camera's y is not vertical


def test_cli_import_export_and_errors(sift_model, tmp_path, monkeypatch, capsys):
    model_dir, images_dir, _ = sift_model
    monkeypatch.setenv("MONOLOC_DATA_DIR", str(tmp_path / "data"))

    def run(*args):
        code, out, err = run_monoloc(monkeypatch, capsys, *args)
        return SimpleNamespace(returncode=code, stdout=out, stderr=err)

    ok = run(
        "map",
        "import",
        "--format",
        "colmap",
        str(model_dir),
        "--images",
        str(images_dir),
        "--map",
        "city",
        "--points",
        "model",
    )
    assert ok.returncode == 0, ok.stderr
    assert "created map city" in ok.stdout
    out = run("map", "export", "--format", "colmap", "--map", "city", str(tmp_path / "out"))
    assert out.returncode == 0 and "8 entries" in out.stdout, out.stderr
    no_model = run(
        "map",
        "import",
        "--format",
        "colmap",
        str(tmp_path / "nowhere"),
        "--images",
        str(images_dir),
        "--map",
        "city",
    )
    assert no_model.returncode != 0
    assert no_model.stderr.strip().startswith("error: ") and "nowhere" in no_model.stderr
    bad_up = run(
        "map",
        "import",
        "--format",
        "colmap",
        str(model_dir),
        "--images",
        str(images_dir),
        "--map",
        "city",
        "--up",
        "x",
    )
    assert bad_up.returncode != 0 and "unknown up axis" in bad_up.stderr
    # Nothing stored was lost or duplicated by the failed attempts.
    from monoloc.server.ingest.manage import find_map
    from monoloc.server.settings import Settings
    from monoloc.server.storage.db import create_engine_for, make_session_factory

    engine = create_engine_for(Settings(data_dir=tmp_path / "data"))
    try:
        assert find_map(make_session_factory(engine), "city").n_entries == 8
    finally:
        engine.dispose()

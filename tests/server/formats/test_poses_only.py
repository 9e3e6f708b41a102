"""COLMAP models with posed images and no 3D points (mapped with known poses), written by
pycolmap: triangulated from their poses with pycolmap at import, or refused in one line
naming why (images missing, too few matches); a refused or failed import leaves no map."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from cli_runner import run_monoloc
from colmap_builder import build_sift_model
from map_checks import query_position_errors_m

from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage.db import session_scope


@pytest.fixture(scope="module")
def sift_model(map_run, tmp_path_factory):
    return build_sift_model(map_run, tmp_path_factory.mktemp("colmap"))


@pytest.fixture(scope="module")
def poses_only(sift_model, tmp_path_factory):
    """The SIFT model with every 3D point deleted (its images keep their 2D points)."""
    import pycolmap

    model_dir, _, truth = sift_model
    reconstruction = pycolmap.Reconstruction(str(model_dir))
    for point_id in list(reconstruction.point3D_ids()):
        reconstruction.delete_point3D(point_id)
    assert reconstruction.num_points3D() == 0 and reconstruction.num_reg_images() == len(truth)
    out = tmp_path_factory.mktemp("poses_only")
    reconstruction.write(str(out))
    return out


@pytest.fixture
def monoloc(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("MONOLOC_DATA_DIR", str(tmp_path / "data"))
    return lambda *args: run_monoloc(monkeypatch, capsys, *args)


def _maps(monoloc) -> str:
    code, out, err = monoloc("map", "list")
    assert code == 0, err
    return out


def _open(tmp_path):
    from monoloc.server.settings import Settings
    from monoloc.server.storage.db import create_engine_for, make_session_factory

    engine = create_engine_for(Settings(data_dir=tmp_path / "data"))
    return engine, make_session_factory(engine)


def test_a_poses_only_model_is_triangulated_from_its_poses(
    poses_only, sift_model, map_run, query_run, monoloc, tmp_path
):
    from monoloc.server.ingest.manage import find_map
    from monoloc.server.map_registry import MapRegistry
    from monoloc.server.settings import Settings
    from monoloc.server.vision.depth import points_from_lidar

    _, images_dir, truth = sift_model
    code, out, err = monoloc(
        "map", "import", "--format", "colmap", str(poses_only), "--images", str(images_dir),
        "--map", "city",
    )  # fmt: skip
    assert code == 0, err
    assert "triangulated" in out and "created map city" in out
    engine, factory = _open(tmp_path)
    try:
        record = find_map(factory, "city")
        with session_scope(factory) as session:
            ids = [s.id for s in entries_repo.list_entries(session, record.id, limit=100)]
            entries = entries_repo.get_entry_data(session, ids)
        # and the map localizes query frames of the same street
        registry = MapRegistry(factory, Settings(data_dir=tmp_path / "data").index_dir)
        errors = query_position_errors_m(registry, record.id, query_run)
    finally:
        engine.dispose()
    assert np.median(errors) < 0.3, errors
    assert len(entries) == len(truth) == 8
    relative = []
    for entry, frame in zip(entries, map_run.frames, strict=True):
        # the known poses are kept exactly (the triangulation holds them fixed)
        np.testing.assert_allclose(entry.T_world_from_cam, frame.T_world_from_cam, atol=1e-6)
        assert len(entry.points_cam) >= 20
        # the triangulated points lie where the LiDAR says the scene is
        scan = map_run.load(frame).source
        lidar, has = points_from_lidar(
            entry.keypoints_px, scan.points_lidar, scan.T_cam_from_lidar, map_run.intrinsics
        )
        relative.extend(np.abs(entry.points_cam[has, 2] - lidar[has, 2]) / lidar[has, 2])
    assert len(relative) > 100 and np.median(relative) < 0.03, np.median(relative)


def test_poses_only_models_that_cannot_be_triangulated_are_refused_leaving_no_map(
    poses_only, sift_model, monoloc, tmp_path
):
    _, images_dir, _ = sift_model
    imported = ["map", "import", "--format", "colmap", str(poses_only), "--map", "city"]
    # the images are not there
    empty = tmp_path / "no_images"
    empty.mkdir()
    code, _, err = monoloc(*imported, "--images", str(empty))
    assert code == 1 and err.count("\n") == 1 and "Traceback" not in err
    assert "no 3D points" in err and "not under" in err and "cannot triangulate" in err
    # images without texture: no features, no verified pair
    blank = tmp_path / "blank"
    blank.mkdir()
    for image in images_dir.iterdir():
        gray = cv2.imread(str(image), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(blank / image.name), np.full_like(gray, 128))
    code, _, err = monoloc(*imported, "--images", str(blank))
    assert code == 1 and err.count("\n") == 1 and "Traceback" not in err
    assert "0 verified image pairs" in err and "too few matches" in err
    # images of another size than the model's camera (resized after mapping)
    small = tmp_path / "small"
    small.mkdir()
    for image in images_dir.iterdir():
        gray = cv2.imread(str(image), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(small / image.name), cv2.resize(gray, (310, 94)))
    code, _, err = monoloc(*imported, "--images", str(small))
    assert code == 1 and err.count("\n") == 1 and "Traceback" not in err
    assert "image is 310x94 but its camera 1 is 620x188" in err
    assert " city " not in _maps(monoloc)


def test_a_failed_import_deletes_the_map_it_created(sift_model, monoloc, tmp_path):
    """Unreadable images: the import fails after creating the map, which goes again."""
    model_dir, images_dir, _ = sift_model
    junk = tmp_path / "junk_images"
    junk.mkdir()
    for image in images_dir.iterdir():
        (junk / image.name).write_bytes(b"not a png")
    code, _, err = monoloc(
        "map", "import", "--format", "colmap", str(model_dir), "--images", str(junk),
        "--map", "city",
    )  # fmt: skip
    assert code == 1 and "Traceback" not in err
    assert err.strip().splitlines()[-1].endswith("unreadable image (not a valid PNG/JPEG)")
    assert " city " not in _maps(monoloc)

"""Mapping cameras with lens distortion: a sim run recorded through a lens (its images
remapped through the issue's plumb_bob lens, or a fisheye) written as a COLMAP model by
pycolmap (OPENCV / OPENCV_FISHEYE camera, SIFT keypoints on the distorted images) and as
a kapture dataset by kapture (OPENCV sensor, LiDAR scans); imported, its entries are
pinhole-consistent (points on their keypoints' pinhole rays at the LiDAR's depth), the
map's camera is the pinhole of the same K, and pinhole query frames localize on it."""

from __future__ import annotations

import dataclasses
import shutil

import cv2
import numpy as np
import pytest
from colmap_builder import build_sift_model, distort_image
from map_checks import query_position_errors_m

from monoloc.core.camera import LensDistortion
from monoloc.core.geometry import invert_rigid, quaternion_xyzw_from_R
from monoloc.server.formats.colmap import read_colmap_model
from monoloc.server.formats.maps import import_sources_into_map
from monoloc.server.formats.model import import_sources
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage.db import session_scope

LENSES = {
    "plumb_bob": LensDistortion("plumb_bob", (-0.28, 0.09, 0.0006, -0.0004)),
    "fisheye": LensDistortion("equidistant", (0.02, -0.005, 0.0, 0.0)),
}


def _lens(map_run, name):
    return dataclasses.replace(map_run.intrinsics, distortion=LENSES[name])


@pytest.fixture(scope="module", params=sorted(LENSES))
def distorted_model(request, map_run, tmp_path_factory):
    lens = _lens(map_run, request.param)
    model_dir, images_dir, truth = build_sift_model(
        map_run, tmp_path_factory.mktemp("distorted"), lens=lens
    )
    return lens, model_dir, images_dir


def _entries(factory, map_id):
    with session_scope(factory) as session:
        ids = [s.id for s in entries_repo.list_entries(session, map_id, limit=1000)]
        return entries_repo.get_entry_data(session, ids)


def _detect(image, kind):
    from monoloc.server.vision.features import extract_features

    if kind == "orb":
        return extract_features(image).keypoints_px
    keypoints = cv2.SIFT_create(nfeatures=3000).detect(image, None)
    return cv2.KeyPoint_convert(keypoints).reshape(-1, 2)


def _assert_pinhole_consistent(entries, map_run, tolerance_px, keypoints="orb"):
    from scipy.spatial import cKDTree

    from monoloc.server.vision.depth import points_from_lidar

    K = map_run.intrinsics.K
    relative, offsets = [], []
    for entry, frame in zip(entries, map_run.frames, strict=True):
        # the keypoints are where the pinhole image the lens distorted has them
        pinhole = _detect(map_run.load(frame).image_gray, keypoints)
        offsets.extend(cKDTree(pinhole).query(entry.keypoints_px)[0])
        np.testing.assert_allclose(entry.T_world_from_cam, frame.T_world_from_cam, atol=1e-6)
        assert len(entry.points_cam) >= 20
        projected = entry.points_cam @ K.T
        np.testing.assert_allclose(
            projected[:, :2] / projected[:, 2:], entry.keypoints_px, atol=tolerance_px
        )
        scan = map_run.load(frame).source
        lidar, has = points_from_lidar(
            entry.keypoints_px, scan.points_lidar, scan.T_cam_from_lidar, map_run.intrinsics
        )
        relative.extend(np.abs(entry.points_cam[has, 2] - lidar[has, 2]) / lidar[has, 2])
    # the keypoints are where a pinhole camera sees the points: the LiDAR agrees there
    assert len(relative) > 100 and np.median(relative) < 0.02, np.median(relative)
    assert np.median(offsets) < 1.0, np.median(offsets)


@pytest.mark.parametrize("points", ["orb", "model"])
def test_a_distorted_colmap_model_imports_pinhole_consistent(
    factory, distorted_model, map_run, points
):
    import pycolmap

    lens, model_dir, images_dir = distorted_model
    (camera,) = pycolmap.Reconstruction(str(model_dir)).cameras.values()
    assert (
        camera.model.name
        == {"plumb_bob": "OPENCV", "equidistant": "OPENCV_FISHEYE"}[lens.distortion.model]
    )
    model = read_colmap_model(model_dir, images_dir)
    assert model.images[0].intrinsics == lens
    sources = import_sources(model, fmt="colmap", up=None, points=points)
    assert sources[0].lens == lens and sources[0].intrinsics == map_run.intrinsics
    record, summaries, _ = import_sources_into_map(factory, f"d-{points}", sources)
    assert summaries[0].entries_added == 8
    assert record.camera == map_run.intrinsics  # the pinhole of the same K
    _assert_pinhole_consistent(
        _entries(factory, record.id), map_run, 0.05 if points == "orb" else 2e-3, points
    )


def test_the_distorted_import_localizes_pinhole_queries(
    factory, settings, distorted_model, query_run
):
    from monoloc.server.map_registry import MapRegistry

    _, model_dir, images_dir = distorted_model
    model = read_colmap_model(model_dir, images_dir)
    record, _, _ = import_sources_into_map(
        factory, "loc", import_sources(model, fmt="colmap", up=None)
    )
    registry = MapRegistry(factory, settings.index_dir)
    errors = query_position_errors_m(registry, record.id, query_run)
    assert np.median(errors) < 0.3, errors


def _pose(kapture, T_a_from_b):
    q = quaternion_xyzw_from_R(T_a_from_b[:3, :3])
    return kapture.PoseTransform(r=[q[3], *q[:3]], t=T_a_from_b[:3, 3].tolist())


def test_a_kapture_dataset_of_a_distorted_camera_with_lidar_imports_pinhole_consistent(
    factory, map_run, sim_city, tmp_path
):
    """kapture's OPENCV sensor with LiDAR scans: the scans project into the undistorted
    image, so the entries equal those of the pinhole run's KITTI ingest up to ORB on a
    remapped image."""
    import kapture
    from kapture.io.csv import kapture_to_dir
    from kapture.io.records import get_record_fullpath

    from monoloc.server.formats.kapture_io import read_kapture

    lens = _lens(map_run, "plumb_bob")
    c = lens
    params = [c.width_px, c.height_px, c.fx, c.fy, c.cx + 0.5, c.cy + 0.5]
    params += list(lens.distortion.coefficients)
    sensors = kapture.Sensors()
    sensors["cam0"] = kapture.Camera(kapture.CameraType.OPENCV, params, name="cam0")
    sensors["lidar0"] = kapture.create_sensor("lidar", [], name="lidar0")
    trajectories, cameras, lidars = (
        kapture.Trajectories(),
        kapture.RecordsCamera(),
        kapture.RecordsLidar(),
    )
    root = tmp_path / "kapture"
    (root / "sensors" / "records_data" / "cam0").mkdir(parents=True)
    (root / "sensors" / "records_data" / "lidar0").mkdir()
    for frame in map_run.frames:
        ts = 10 + frame.index
        loaded = map_run.load(frame)
        T_cam_from_world = invert_rigid(frame.T_world_from_cam)
        trajectories[ts, "cam0"] = _pose(kapture, T_cam_from_world)
        T_lidar_from_world = invert_rigid(loaded.source.T_cam_from_lidar) @ T_cam_from_world
        trajectories[ts, "lidar0"] = _pose(kapture, T_lidar_from_world)
        cameras[ts, "cam0"] = f"cam0/{frame.index:06d}.png"
        cv2.imwrite(
            get_record_fullpath(str(root), cameras[ts, "cam0"]),
            distort_image(loaded.image_gray, lens),
        )
        lidars[ts, "lidar0"] = f"lidar0/{frame.index:06d}.bin"
        shutil.copyfile(
            sim_city / "sequences" / "00" / "velodyne" / f"{frame.index:06d}.bin",
            get_record_fullpath(str(root), lidars[ts, "lidar0"]),
        )
    kapture_to_dir(
        str(root),
        kapture.Kapture(
            sensors=sensors, trajectories=trajectories, records_camera=cameras, records_lidar=lidars
        ),
    )
    model = read_kapture(root)
    assert model.images[0].intrinsics == lens
    record, summaries, _ = import_sources_into_map(
        factory, "k", import_sources(model, fmt="kapture", up=None)
    )
    assert summaries[0].entries_added == 8 and record.camera == map_run.intrinsics
    _assert_pinhole_consistent(_entries(factory, record.id), map_run, 1e-3)


def test_a_thin_prism_kapture_sensor_is_refused_by_name(tmp_path):
    import kapture
    from kapture.io.csv import kapture_to_dir

    from monoloc.core.errors import InvalidInputError
    from monoloc.server.formats.kapture_io import read_kapture

    sensors = kapture.Sensors()
    params = [640, 480, 500, 500, 320, 240] + [0.01] * 8
    sensors["cam0"] = kapture.Camera(kapture.CameraType.THIN_PRISM_FISHEYE, params, name="cam0")
    records = kapture.RecordsCamera()
    records[0, "cam0"] = "cam0/0.png"
    trajectories = kapture.Trajectories()
    trajectories[0, "cam0"] = kapture.PoseTransform(r=[1, 0, 0, 0], t=[0, 0, 0])
    kapture_to_dir(
        str(tmp_path),
        kapture.Kapture(sensors=sensors, records_camera=records, trajectories=trajectories),
    )
    with pytest.raises(InvalidInputError, match="THIN_PRISM_FISHEYE is not one monoloc knows"):
        read_kapture(tmp_path)

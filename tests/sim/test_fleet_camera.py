"""The sim's fleet camera (issue 48): another size, focal length, lens and mounting than
the mapping camera. A distorted render puts a known 3D point where OpenCV's own lens
model projects it, its keypoints undistorted fall where the pinhole render of the same
pose has them, and the fleet run writes its camera (calib.txt's P0, camera.json) and the
fleet camera's own poses."""

from __future__ import annotations

import dataclasses
import json
import math

import cv2
import numpy as np
import pytest
import yaml

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.core.formats import kitti, tum
from monoloc.core.geometry import T_world_from_cam_planar, kitti_to_zup
from monoloc.sim.camera import CameraConfig, Lighting, render
from monoloc.sim.fleet_camera import FLEET_CAMERAS, FleetCameraConfig
from monoloc.sim.generate import GenerateConfig, generate_dataset
from monoloc.sim.lens import lens_remap
from monoloc.sim.lidar import LidarConfig
from monoloc.sim.recording import RecordingErrors
from monoloc.sim.scene import KIND_WALL, SceneBuilder
from monoloc.sim.shapes import add_wall
from monoloc.sim.textures import TextureBank, TextureLayers, TextureSpec

LENSES = ("issue48", "issue48_equidistant")
QUIET = CameraConfig(shot_noise=0.0, read_noise=0.0)
WALL_X_M = 8.0
CAMERA_HEIGHT_M = 1.5


def _flat(value):
    def make(spec, rng):
        return TextureLayers(albedo=np.full((spec.height_px, spec.width_px), value, np.uint8))

    return make


def _cells(spec, rng):
    """Cells of random gray levels: sharp corners everywhere, none repeating."""
    cells = rng.integers(0, 256, (spec.height_px // 16, spec.width_px // 16)).astype(np.uint8)
    return TextureLayers(albedo=np.kron(cells, np.ones((16, 16), np.uint8)))


BANK = TextureBank({"dark": _flat(25), "white": _flat(240), "cells": _cells})


def _back_wall(builder, spec, x_m=WALL_X_M, ppm=10.0) -> None:
    """A wall across every ray of the camera at the origin looking along +x."""
    add_wall(builder, (x_m, -40.0), (x_m, 40.0), -20.0, 20.0, spec, ppm, KIND_WALL, 80.0)


def _camera(name: str, scale: float = 0.5) -> CameraIntrinsics:
    return FleetCameraConfig.preset(name).intrinsics(scale)


@pytest.mark.parametrize("name", LENSES)
def test_a_known_point_lands_where_the_lens_model_projects_it(name):
    camera = _camera(name)
    T_world_from_cam = T_world_from_cam_planar(0.0, 0.0, 0.0, CAMERA_HEIGHT_M)
    # marker centres at pixels spread over the image, corners included, placed in 3D on
    # the rays OpenCV's undistortion gives them, 5 cm in front of the wall
    w, h = camera.width_px, camera.height_px
    targets = np.array([(u, v) for u in np.linspace(12, w - 13, 5) for v in (12, h / 2, h - 13)])
    K, D = camera.K, np.array(camera.distortion.coefficients)
    depth_m = WALL_X_M - 0.05
    if camera.distortion.model == "equidistant":
        rays = cv2.fisheye.undistortPoints(targets.reshape(-1, 1, 2), K, D).reshape(-1, 2)
    else:
        rays = cv2.undistortPoints(targets.reshape(-1, 1, 2), K, D).reshape(-1, 2)
    points_cam = np.c_[rays, np.ones(len(rays))] * depth_m
    points_world = points_cam @ T_world_from_cam[:3, :3].T + T_world_from_cam[:3, 3]
    builder = SceneBuilder()
    _back_wall(builder, TextureSpec("dark", 64, 64, 0))
    half = 0.012 * depth_m  # ~ 4 px across
    for x, y, z in points_world:
        add_wall(
            builder, (x, y - half), (x, y + half), z - half, z + half,
            TextureSpec("white", 16, 16, 0), 100.0, KIND_WALL,
        )  # fmt: skip
    frame = render(
        builder.build(), BANK, T_world_from_cam, camera, Lighting(), np.random.default_rng(0), QUIET
    )
    assert frame.image.shape == (h, w)
    # where OpenCV's forward lens model puts the 3D points (projectPoints, not the inverse
    # the renderer used)
    zero = np.zeros(3)
    if camera.distortion.model == "equidistant":
        expected = cv2.fisheye.projectPoints(points_cam.reshape(-1, 1, 3), zero, zero, K, D)[0]
    else:
        expected = cv2.projectPoints(points_cam, zero, zero, K, D)[0]
    expected = expected.reshape(-1, 2)
    pinhole_px = points_cam[:, :2] / points_cam[:, 2:] * [camera.fx, camera.fy] + K[:2, 2]
    assert np.abs(pinhole_px - expected).max() > 15  # a real lens: pinhole would be far off
    bright = (frame.image > 128).astype(np.uint8)
    n, _, stats, centroids = cv2.connectedComponentsWithStats(bright)
    found = centroids[1:][stats[1:, cv2.CC_STAT_AREA] >= 3]
    assert len(found) == len(expected)
    weights = frame.image.astype(np.float64)
    for target in expected:
        near = found[np.argmin(np.linalg.norm(found - target, axis=1))]
        # intensity-weighted centroid in a window about the blob
        x0, y0 = int(round(near[0])) - 5, int(round(near[1])) - 5
        patch = weights[max(y0, 0) : y0 + 11, max(x0, 0) : x0 + 11]
        patch = np.where(patch > 128, patch - 25, 0.0)
        yy, xx = np.mgrid[
            max(y0, 0) : max(y0, 0) + patch.shape[0], max(x0, 0) : max(x0, 0) + patch.shape[1]
        ]
        centre = np.array([(xx * patch).sum(), (yy * patch).sum()]) / patch.sum()
        assert np.linalg.norm(centre - target) < 1.0, (centre, target)


def _textured_scene():
    """Three walls of random cells at different depths before a far one."""
    builder = SceneBuilder()
    blobs = [TextureSpec("cells", 512, 512, seed) for seed in range(4)]
    _back_wall(builder, blobs[0], x_m=14.0, ppm=30.0)
    add_wall(builder, (6.0, -6.0), (7.0, -1.0), -1.5, 3.0, blobs[1], 60.0, KIND_WALL)
    add_wall(builder, (9.0, 0.5), (8.0, 5.0), -1.5, 4.0, blobs[2], 50.0, KIND_WALL)
    add_wall(builder, (4.0, -1.0), (4.0, 1.2), 0.8, 2.2, blobs[3], 120.0, KIND_WALL)
    return builder.build()


@pytest.mark.parametrize("name", LENSES)
def test_undistorted_keypoints_of_the_distorted_render_match_the_pinhole_render(name):
    from monoloc.server.vision.undistort import undistort_pixels

    camera = _camera(name, scale=1.0)
    scene = _textured_scene()
    T_world_from_cam = T_world_from_cam_planar(0.0, 0.0, 0.0, CAMERA_HEIGHT_M)

    def shot(intrinsics):
        return render(
            scene, BANK, T_world_from_cam, intrinsics, Lighting(), np.random.default_rng(0),
            QUIET, exposure=1.0,
        ).image  # fmt: skip

    distorted, pinhole = shot(camera), shot(camera.pinhole)
    # corners found in the distorted render, to a tenth of a pixel, then undistorted
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 0.001)
    found = cv2.goodFeaturesToTrack(distorted, 400, 0.05, 12, blockSize=5)
    seen = cv2.cornerSubPix(distorted, found, (5, 5), (-1, -1), criteria).reshape(-1, 2)
    undistorted = undistort_pixels(seen, camera)
    inside = np.all(
        (undistorted > 8) & (undistorted < [camera.width_px - 9, camera.height_px - 9]), 1
    )
    assert inside.sum() > 150
    seen, undistorted = seen[inside], undistorted[inside]
    # the same corners in the pinhole render, searched from the undistorted pixel rounded
    start = np.round(undistorted).astype(np.float32).reshape(-1, 1, 2)
    ideal = cv2.cornerSubPix(pinhole, start, (5, 5), (-1, -1), criteria).reshape(-1, 2)
    error = np.linalg.norm(undistorted - ideal, axis=1)
    moved = np.linalg.norm(seen - ideal, axis=1)
    assert np.percentile(moved, 90) > 10  # the lens moved them, far from the centre a lot
    assert np.median(error) < 0.25
    assert np.mean(error < 1.0) > 0.9
    # and ORB, the server's own features, matched between the two renders
    orb = cv2.ORB_create(3000)
    kp_d, des_d = orb.detectAndCompute(distorted, None)
    kp_p, des_p = orb.detectAndCompute(pinhole, None)
    matches = [
        m
        for m in cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(des_d, des_p)
        if m.distance < 40
    ]
    assert len(matches) > 200
    orb_seen = np.array([kp_d[m.queryIdx].pt for m in matches])
    orb_ideal = np.array([kp_p[m.trainIdx].pt for m in matches])
    orb_error = np.linalg.norm(undistort_pixels(orb_seen, camera) - orb_ideal, axis=1)
    orb_raw = np.linalg.norm(orb_seen - orb_ideal, axis=1)
    print(
        f"ORB: median {np.median(orb_error):.3f} px, {np.mean(orb_error < 2):.2f} within 2 px "
        f"(raw: {np.mean(orb_raw < 2):.2f})"
    )
    # ORB's positions are whole pixels of its pyramid levels, and some matches are wrong
    assert np.median(orb_error) < 1.0
    assert np.mean(orb_error < 2.0) > 0.7 > 0.4 > np.mean(orb_raw < 2.0)


def test_the_canvas_holds_every_ray_of_the_lens():
    camera = _camera("issue48", scale=1.0)
    lens = lens_remap(camera)
    assert lens.canvas.distortion is None
    assert (lens.canvas.fx, lens.canvas.fy) == (camera.fx, camera.fy)
    assert lens.canvas.width_px > camera.width_px and lens.canvas.height_px > camera.height_px
    assert lens.map_x_px.min() >= 1 and lens.map_x_px.max() <= lens.canvas.width_px - 2
    assert lens.map_y_px.min() >= 1 and lens.map_y_px.max() <= lens.canvas.height_px - 2
    # a barrel lens whose image no pinhole ray reaches at the corners: refused by name
    wild = FleetCameraConfig(distortion=(-0.9, 0.0, 0.0, 0.0), focal_px=200.0)
    with pytest.raises(InvalidInputError, match="cannot be inverted over the 1024x576 image"):
        GenerateConfig(runs=("map", "fleet"), fleet_camera=wild).validate()
    GenerateConfig(runs=("map", "query"), fleet_camera=wild).validate()  # not used: fine
    with pytest.raises(InvalidInputError, match="unknown fleet camera"):
        FleetCameraConfig.preset("gopro")


def test_the_preset_is_issue_48s_fleet_camera():
    camera = FLEET_CAMERAS["issue48"]
    k = camera.intrinsics()
    assert (k.width_px, k.height_px, k.fx, k.fy) == (1024, 576, 640.0, 640.0)
    assert k.distortion.model == "plumb_bob"
    assert k.distortion.coefficients == (-0.28, 0.09, 0.0006, -0.0004)
    T = camera.T_mapcam_from_cam()  # OpenCV axes of the mapping camera
    np.testing.assert_allclose(T[:3, 3], [0.0, 0.23, 0.0], atol=1e-12)  # 0.23 m lower
    axis = T[:3, 2]  # the fleet camera's optical axis in the mapping camera's frame
    assert math.degrees(math.asin(axis[1])) == pytest.approx(3.0)  # pitched down
    assert math.degrees(math.atan2(-axis[0], axis[2])) == pytest.approx(0.8)  # turned left


@pytest.fixture(scope="module")
def fleet_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("fleet")
    config = GenerateConfig(
        seed=3,
        runs=("map", "query", "fleet"),
        max_frames=3,
        image_scale=0.5,
        errors=RecordingErrors.none(),
        lidar=LidarConfig(azimuth_steps=500),
        fleet_camera=dataclasses.replace(FLEET_CAMERAS["issue48"], ahead_m=-0.4, left_m=0.1),
    )
    generate_dataset(config, root)
    return root, config


def test_the_fleet_run_writes_its_camera_and_its_own_poses(fleet_dataset):
    root, config = fleet_dataset
    meta = json.loads((root / "dataset.json").read_text())
    fleet = next(s for s in meta["sequences"] if s["run"] == "fleet")
    assert fleet["camera"]["distortion_model"] == "plumb_bob"
    camera = config.fleet_camera.intrinsics(0.5)
    seq = kitti.sequence_dir(root, fleet["id"])
    images = sorted((seq / "image_0").glob("*.png"))
    query = next(s for s in meta["sequences"] if s["run"] == "query")
    assert len(images) == fleet["frames"] == query["frames"] >= 2  # cut to the map's stretch
    assert fleet["seed"] == query["seed"]  # one recording of one drive (pose errors, signals)
    assert (seq / "vehicle.txt").read_bytes() == (
        kitti.sequence_dir(root, query["id"]) / "vehicle.txt"
    ).read_bytes()
    assert cv2.imread(str(images[0]), cv2.IMREAD_UNCHANGED).shape == (288, 512)
    np.testing.assert_allclose(
        kitti.read_calib_file(seq / "calib.txt").intrinsics(512, 288).K, camera.K
    )
    assert tum.read_run_camera(seq, images[0]) == camera  # camera.json, lens included
    # truth: the query's drive (the same run to the metre), seen from the fleet camera
    T_query = kitti_to_zup(kitti.read_poses_file(kitti.poses_path(root, query["id"])))
    T_fleet = kitti_to_zup(kitti.read_poses_file(kitti.poses_path(root, fleet["id"])))
    np.testing.assert_allclose(
        T_fleet, T_query @ config.fleet_camera.T_mapcam_from_cam(), atol=1e-6
    )
    # and its mounting as dataset.json tells it
    T_vehicle_from_cam = np.array(fleet["T_vehicle_from_cam"])
    T_vehicle_from_mapcam = np.array(meta["rig"]["T_vehicle_from_cam0"])
    np.testing.assert_allclose(
        T_vehicle_from_cam[:3, 3] - T_vehicle_from_mapcam[:3, 3], [-0.4, 0.1, -0.23], atol=1e-9
    )


def test_the_vehicle_replays_the_fleet_run_with_its_camera(fleet_dataset):
    from monoloc.client.replay import read_run

    root, config = fleet_dataset
    meta = json.loads((root / "dataset.json").read_text())
    fleet = next(s for s in meta["sequences"] if s["run"] == "fleet")
    run = read_run(root, fleet["id"])
    assert run.intrinsics == config.fleet_camera.intrinsics(0.5)
    # and where it sits on the car, from the camera file beside the frames: camera.yaml
    # in ROS's layout, the same as camera.json
    seq = root / "sequences" / fleet["id"]
    camera = json.loads((seq / "camera.json").read_text())
    np.testing.assert_allclose(
        run.mounting.T_vehicle_from_cam, camera["T_vehicle_from_cam"], atol=1e-9
    )
    ros = yaml.safe_load((seq / "camera.yaml").read_text())
    assert ros["distortion_model"] == camera["distortion_model"]
    assert ros["distortion_coefficients"]["data"] == camera["D"]
    assert ros["camera_matrix"]["data"] == np.ravel(camera["K"]).tolist()
    assert (ros["image_width"], ros["image_height"]) == (camera["width"], camera["height"])


def test_datasets_without_the_fleet_run_are_as_before(fleet_dataset, tmp_path):
    root, config = fleet_dataset
    again = dataclasses.replace(config, runs=("map", "query"), fleet_camera=FleetCameraConfig())
    generate_dataset(again, tmp_path)
    for name in ("00", "01"):
        for sub in ("calib.txt", "times.txt", "vehicle.txt", "image_0/000001.png"):
            assert (tmp_path / "sequences" / name / sub).read_bytes() == (
                root / "sequences" / name / sub
            ).read_bytes()
        assert not (tmp_path / "sequences" / name / "camera.json").exists()


def test_sim_generate_takes_a_fleet_camera_by_name_and_refuses_an_unknown_one(
    monkeypatch, capsys, tmp_path
):
    import sys

    from monoloc import cli

    def run(*argv: str) -> tuple[int, str]:
        monkeypatch.setattr(sys, "argv", ["monoloc", "sim", "generate", *argv])
        try:
            cli.main()
            code = 0
        except SystemExit as exited:
            code = exited.code
        return code, capsys.readouterr().err

    base = ("--runs", "map,fleet", "--frames", "1", "--scale", "0.25", "--no-errors")
    code, err = run("--out", str(tmp_path / "bad"), *base, "--fleet-camera", "gopro")
    assert code != 0 and "unknown fleet camera 'gopro'" in err
    assert not (tmp_path / "bad").exists()
    out = tmp_path / "fisheye"
    code, err = run("--out", str(out), *base, "--fleet-camera", "issue48_equidistant")
    assert code in (0, None), err
    camera = json.loads((out / "sequences" / "01" / "camera.json").read_text())
    assert camera["distortion_model"] == "equidistant" and camera["fx"] == 130.0

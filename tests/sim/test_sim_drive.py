import math

import numpy as np
import pytest

from monoloc.core.formats import kitti
from monoloc.core.formats.vehicle import read_vehicle
from monoloc.core.geometry import invert_rigid, kitti_to_zup
from monoloc.sim.camera import Lighting, render
from monoloc.sim.generate import GenerateConfig
from monoloc.sim.recording import RecordingErrors
from monoloc.sim.scene import concat_scenes
from monoloc.sim.textures import TextureBank
from monoloc.sim.urban.city import build_city, parked_cars
from monoloc.sim.urban.info import kitti_world
from monoloc.sim.urban.record import prepare_run_files, write_run_metadata
from monoloc.sim.urban.runs import plan_runs, true_camera_poses
from monoloc.sim.urban.textures import URBAN_TEXTURES

CONFIG = GenerateConfig(seed=0, runs=("map", "query", "night", "offcenter"))


@pytest.fixture(scope="module")
def city_and_plans():
    city = build_city(CONFIG.city_config(), CONFIG.seed)
    return city, {p.kind: p for p in plan_runs(city, CONFIG)}


def test_query_frames_have_a_map_frame_within_2m(city_and_plans):
    _, plans = city_and_plans
    map_xy = true_camera_poses(plans["map"], CONFIG.rig)[:, :2, 3]
    for kind in ("query", "night"):
        pose = true_camera_poses(plans[kind], CONFIG.rig)
        xy = pose[:, :2, 3]
        dist = np.linalg.norm(xy[:, None, :] - map_xy[None, :, :], axis=2)
        nearest = dist.min(axis=1)
        assert len(xy) > 500
        assert nearest.max() < 2.0, kind
        assert nearest.mean() > 0.3  # the query really is off the map's line


def test_capped_query_and_night_runs_stop_where_their_map_run_ends():
    # Each run drives at its own speed: capped at 120 frames, seed 5's map run covers
    # 115 m, its query 140 m and its night 140 m against the night map's 126 m, and the
    # last frames of both would have had no map at all
    config = GenerateConfig(seed=5, runs=("map", "query", "night", "nightmap"), max_frames=120)
    city = build_city(config.city_config(), config.seed)
    plans = {p.kind: p for p in plan_runs(city, config)}
    assert len(plans["map"].frame_times_s) == len(plans["nightmap"].frame_times_s) == 120
    for kind, against in (("query", "map"), ("night", "nightmap")):
        ref_xy = true_camera_poses(plans[against], config.rig)[:, :2, 3]
        xy = true_camera_poses(plans[kind], config.rig)[:, :2, 3]
        nearest = np.linalg.norm(xy[:, None] - ref_xy[None], axis=2).min(axis=1)
        assert nearest.max() < 2.0, kind
        assert 80 <= len(xy) < 120, kind  # cut at the end only


def test_offcenter_run_oscillates_around_the_lane(city_and_plans):
    _, plans = city_and_plans
    map_xy = true_camera_poses(plans["map"], CONFIG.rig)[:, :2, 3]
    off_xy = true_camera_poses(plans["offcenter"], CONFIG.rig)[:, :2, 3]
    nearest = np.linalg.norm(off_xy[:, None] - map_xy[None], axis=2).min(axis=1)
    assert 0.2 < np.percentile(nearest, 90) < 2.0


def _integration_errors(tmp_path, plan, errors: RecordingErrors, window: int = 100):
    """End-point errors (m) of integrating vehicle.txt over windows of ``window`` frames
    against the ground-truth rear-axle path recovered from poses/NN.txt."""
    config = GenerateConfig(**{**CONFIG.__dict__, "errors": errors})
    written = prepare_run_files(plan, config, tmp_path)
    write_run_metadata(plan, written, kitti_world(written.T_written[0]), config, tmp_path)
    signals = read_vehicle(kitti.sequence_dir(tmp_path, plan.seq_id) / "vehicle.txt")
    T_cam = kitti_to_zup(kitti.read_poses(tmp_path / "poses" / f"{plan.seq_id}.txt"))
    T_vehicle = T_cam @ invert_rigid(config.rig.T_vehicle_from_cam())
    truth = np.stack(
        [
            T_vehicle[:, 0, 3],
            T_vehicle[:, 1, 3],
            np.arctan2(T_vehicle[:, 1, 0], T_vehicle[:, 0, 0]),
        ],
        axis=1,
    )
    t, v, w = signals.timestamps_s, signals.speed_mps, signals.yaw_rate_radps
    errors_m, dist_m = [], []
    for start in range(0, len(t) - window, window):
        x, y, psi = truth[start]
        for k in range(start, start + window):
            dt = t[k + 1] - t[k]
            vm, wm = 0.5 * (v[k] + v[k + 1]), 0.5 * (w[k] + w[k + 1])
            x += vm * math.cos(psi + 0.5 * wm * dt) * dt
            y += vm * math.sin(psi + 0.5 * wm * dt) * dt
            psi += wm * dt
        errors_m.append(math.hypot(x - truth[start + window, 0], y - truth[start + window, 1]))
        dist_m.append(float(np.sum(v[start : start + window]) * 0.1))
    return np.array(errors_m), np.array(dist_m)


def test_vehicle_txt_integrates_to_the_ground_truth_path(tmp_path, city_and_plans):
    _, plans = city_and_plans
    plan = plans["map"]
    exact, _ = _integration_errors(tmp_path / "exact", plan, RecordingErrors.none())
    assert len(exact) >= 5
    assert exact.max() < 0.25  # 10 s windows: only the 10 Hz integration error remains
    e = RecordingErrors()
    noisy, dist = _integration_errors(tmp_path / "noisy", plan, e)
    # 3-sigma bound of the configured errors over each 10 s window of distance d: speed
    # scale and bias, yaw-rate bias (heading error growing linearly) and white noise
    # (random-walk heading), plus the written poses' own error at both ends.
    T, dt = 10.0, 0.1
    bound = (
        0.25
        + 2 * e.pose_error_m
        + 3
        * (
            e.speed_scale_error * dist
            + e.speed_bias_mps * T
            + e.yaw_rate_bias_radps * T * dist / 2
            + e.yaw_rate_noise_radps * math.sqrt(T * dt) * dist / math.sqrt(3)
            + e.speed_noise_mps * math.sqrt(T * dt)
        )
    )
    assert np.all(noisy < bound)
    assert noisy.mean() > exact.mean()  # the configured errors are really applied


def test_day_frames_have_enough_orb_features(city_and_plans):
    """METHOD's features: ORB(1000) after a 5x5 Gaussian blur, at KITTI resolution."""
    import cv2

    city, plans = city_and_plans
    plan = plans["map"]
    scene = concat_scenes([city.static, parked_cars(city, 0)])
    bank = TextureBank(URBAN_TEXTURES)
    poses = true_camera_poses(plan, CONFIG.rig)
    orb = cv2.ORB_create(1000)
    counts = []
    for k in (0, len(poses) // 3, 2 * len(poses) // 3):
        frame = render(
            scene, bank, poses[k], CONFIG.intrinsics(), plan.lighting, np.random.default_rng(k)
        )
        counts.append(len(orb.detect(cv2.GaussianBlur(frame.image, (5, 5), 0), None)))
    assert plan.lighting == Lighting.preset("day", np.random.default_rng([0, 0, 1]))
    assert np.mean(counts) >= 500, counts


def test_nightmap_run_drives_the_map_lane_at_night():
    config = GenerateConfig(seed=0, runs=("map", "nightmap"))
    city = build_city(config.city_config(), config.seed)
    plans = {p.kind: p for p in plan_runs(city, config)}
    map_xy = true_camera_poses(plans["map"], config.rig)[:, :2, 3]
    night_xy = true_camera_poses(plans["nightmap"], config.rig)[:, :2, 3]
    nearest = np.linalg.norm(night_xy[:, None] - map_xy[None], axis=2).min(axis=1)
    assert np.percentile(nearest, 95) < 1.0  # the lane centre, like the map
    assert plans["nightmap"].lighting.name == "night" and plans["map"].lighting.name == "day"
    # Adding the kind did not change the seeds of the others.
    reference = {p.kind: p for p in plan_runs(city, CONFIG)}["map"]
    assert np.array_equal(plans["map"].frame_times_s, reference.frame_times_s)


def test_trainnight_run_drives_the_train_route_at_night():
    config = GenerateConfig(seed=0, runs=("train", "trainnight"))
    city = build_city(config.city_config(), config.seed)
    plans = {p.kind: p for p in plan_runs(city, config)}
    assert plans["trainnight"].district == plans["train"].district == "train"
    train_xy = true_camera_poses(plans["train"], config.rig)[:, :2, 3]
    night_xy = true_camera_poses(plans["trainnight"], config.rig)[:, :2, 3]
    nearest = np.linalg.norm(night_xy[:, None] - train_xy[None], axis=2).min(axis=1)
    assert np.percentile(nearest, 95) < 1.0  # the training route, not the map's streets
    assert plans["trainnight"].lighting.name == "night" and plans["train"].lighting.name == "day"
    assert plans["trainnight"].car_variant != plans["train"].car_variant
    # Appending the kind did not change the seeds of the others.
    alone = GenerateConfig(seed=0, runs=("train",))
    reference = plan_runs(city, alone)[0]
    assert np.array_equal(plans["train"].frame_times_s, reference.frame_times_s)
    assert np.array_equal(plans["train"].states.x_m, reference.states.x_m)

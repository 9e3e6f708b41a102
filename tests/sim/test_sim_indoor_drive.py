"""The indoor world and its runs: track, furniture, drives, vehicle signals, realism."""

import math

import numpy as np
import pytest

from monoloc.core.formats import tum
from monoloc.core.formats.vehicle import read_vehicle
from monoloc.core.geometry import invert_rigid
from monoloc.sim import tum_writer as tw
from monoloc.sim.generate import GenerateConfig
from monoloc.sim.indoor.generate import (
    indoor_config_for,
    render_rgbd,
    run_camera_config,
    run_scene,
    write_run_metadata,
)
from monoloc.sim.indoor.infield import obstacles_scene
from monoloc.sim.indoor.plan import T_world_from_cam_at, plan_indoor_runs
from monoloc.sim.indoor.room import room_bounds
from monoloc.sim.indoor.sensors import IndoorErrors
from monoloc.sim.indoor.track import centre_line, curvature_closed, distance_to_line
from monoloc.sim.indoor.world import build_world
from monoloc.sim.recording import RecordingErrors
from monoloc.sim.scene import KIND_GROUND

SEED = 4
CONFIG = GenerateConfig(scenario="indoor", seed=SEED, runs=("map", "query", "train", "offcenter"))


@pytest.fixture(scope="module")
def world_and_plans():
    indoor = indoor_config_for(CONFIG)
    world = build_world(indoor.rooms(), SEED)
    plans = plan_indoor_runs(world, indoor, CONFIG.runs, SEED)
    return indoor, world, {p.run: p for p in plans}


def _xy(indoor, plan):
    return T_world_from_cam_at(plan, indoor.rig, plan.rgb_times_s)[:, :2, 3]


def test_track_fits_the_room_and_furniture_stays_off_it(world_and_plans):
    indoor, world, _ = world_and_plans
    for room in world.rooms.values():
        cfg = room.config
        line = centre_line(room.track)
        x0, y0, x1, y1 = room_bounds(cfg)
        wall_gap = np.min(
            np.stack([line[:, 0] - x0, x1 - line[:, 0], line[:, 1] - y0, y1 - line[:, 1]]), axis=0
        )
        assert wall_gap.min() >= cfg.clearance_m - 1e-6
        assert np.abs(curvature_closed(line)).max() <= 1.0 / cfg.min_turn_radius_m + 1e-6
        dense = centre_line(room.track, 4000)
        for scene in (
            room.static,
            obstacles_scene(room.slots, 7, 0),
            obstacles_scene(room.slots, 7, 1),
        ):
            q = scene.quads
            inside = np.all(np.abs(q.origin[:, :2] - np.array(cfg.centre_xy)) < 10, axis=1)
            furniture = inside & (q.kind != KIND_GROUND) & (q.origin[:, 2] < cfg.height_m - 0.01)
            corners = scene.quads.corners()[furniture].reshape(-1, 3)[:, :2]
            on_walls = np.isclose(corners[:, 0], x0) | np.isclose(corners[:, 0], x1)
            on_walls |= np.isclose(corners[:, 1], y0) | np.isclose(corners[:, 1], y1)
            assert distance_to_line(corners[~on_walls], dense).min() > cfg.track_width_m / 2
    assert len(world.rooms["main"].slots) >= 6


def test_query_frames_have_a_map_frame_within_0_3m(world_and_plans):
    """The 1:10 version of the outdoor 2 m bar: retrieval always has a right answer."""
    indoor, _, plans = world_and_plans
    map_xy = _xy(indoor, plans["map"])
    for run in ("query", "offcenter"):
        xy = _xy(indoor, plans[run])
        nearest = np.linalg.norm(xy[:, None] - map_xy[None], axis=2).min(axis=1)
        assert len(xy) > 150
        assert nearest.max() < 0.3, run
        assert nearest.mean() > 0.03, run  # really off the map's line
    train_xy = _xy(indoor, plans["train"])
    assert np.linalg.norm(train_xy[:, None] - map_xy[None], axis=2).min() > 20.0


def test_runs_drive_at_about_one_metre_per_second(world_and_plans):
    _, _, plans = world_and_plans
    for plan in plans.values():
        speed = plan.states.sample(plan.rgb_times_s)["speed_mps"]
        assert 0.7 < speed.min() and speed.max() < 1.3 and abs(speed.mean() - 1.0) < 0.15


def _integration_errors(tmp_path, indoor, plan, window=45):
    """End-point errors (m) of integrating vehicle.txt over windows of ``window`` frames
    (3 s) against the rear-axle path recovered from groundtruth.txt."""
    write_run_metadata(CONFIG, indoor, plan, tmp_path)
    run = tmp_path / plan.run
    signals = read_vehicle(run / "vehicle.txt")
    gt = tum.read_trajectory(run / "groundtruth.txt")
    gt_t, T_gt = gt.timestamps_s, gt.T_world_from_cam
    T_cam = np.stack([tw.pose_at(gt_t, T_gt, t) for t in signals.timestamps_s])
    T_vehicle = T_cam @ invert_rigid(indoor.rig.T_vehicle_from_cam())
    yaw = np.arctan2(T_vehicle[:, 1, 0], T_vehicle[:, 0, 0])
    t, v, w = signals.timestamps_s, signals.speed_mps, signals.yaw_rate_radps
    errors = []
    for start in range(0, len(t) - window, window):
        x, y, psi = T_vehicle[start, 0, 3], T_vehicle[start, 1, 3], yaw[start]
        for k in range(start, start + window):
            dt = t[k + 1] - t[k]
            vm, wm = 0.5 * (v[k] + v[k + 1]), 0.5 * (w[k] + w[k + 1])
            x += vm * math.cos(psi + 0.5 * wm * dt) * dt
            y += vm * math.sin(psi + 0.5 * wm * dt) * dt
            psi += wm * dt
        end = T_vehicle[start + window, :2, 3]
        errors.append(math.hypot(x - end[0], y - end[1]))
    return np.array(errors)


def test_vehicle_txt_integrates_to_the_ground_truth_path(tmp_path, world_and_plans):
    indoor, _, plans = world_and_plans
    from dataclasses import replace

    exact = _integration_errors(
        tmp_path / "exact", replace(indoor, errors=IndoorErrors.none()), plans["map"]
    )
    assert len(exact) >= 4
    assert exact.max() < 0.01  # 3 s windows at 15 Hz: only the integration error remains
    e = IndoorErrors()
    noisy = _integration_errors(tmp_path / "noisy", indoor, plans["map"])
    # 3-sigma bound over 3 s (~3 m): speed scale and bias, yaw-rate bias and white noise,
    # plus the motion capture's own noise at both ends.
    T, dt, dist = 3.0, 1.0 / 15.0, 3.2
    bound = (
        0.01
        + 2 * 3 * e.mocap_position_noise_m
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


def test_errors_off_when_the_recording_errors_are_off():
    exact = indoor_config_for(GenerateConfig(scenario="indoor", errors=RecordingErrors.none()))
    assert exact.errors == IndoorErrors.none()
    assert indoor_config_for(GenerateConfig(scenario="indoor")).errors == IndoorErrors()


def test_frames_have_enough_orb_features(world_and_plans):
    """METHOD's features: ORB(1000) after a 5x5 Gaussian blur, at D435 resolution, over
    frames spread around the map lap (bare walls included)."""
    import cv2

    indoor, _, plans = world_and_plans
    plan = plans["map"]
    scene, bank = run_scene(CONFIG, indoor, plan)
    orb = cv2.ORB_create(1000)
    picks = np.linspace(0, len(plan.rgb_times_s) - 1, 8).astype(int)
    T = T_world_from_cam_at(plan, indoor.rig, plan.rgb_times_s[picks])
    counts = []
    for i, k in enumerate(picks):
        image, _, _ = render_rgbd(
            scene,
            bank,
            T[i],
            T[i],
            indoor.intrinsics,
            plan.lighting,
            run_camera_config(indoor, plan),
            indoor.errors,
            indoor.render,
            np.random.default_rng(int(k)),
        )
        assert image.shape == (480, 640)
        counts.append(len(orb.detect(cv2.GaussianBlur(image, (5, 5), 0), None)))
    assert np.mean(counts) >= 300, counts

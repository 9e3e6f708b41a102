"""The 1:10 car's own errors (issue 51): the tracker's clock offset and hand-eye residual
in the recorded truth, the camera calibration's residual, the RGB sensor's rolling
shutter, and the closed loop judged against the recorded truth."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from monoloc.sim.indoor.camera_motion import rolling_shutter
from monoloc.sim.indoor.sensors import (
    D435_COLOR,
    IndoorErrors,
    calibrated_intrinsics,
    hand_eye_residual,
    poses_at,
    recorded_truth,
)


def _straight_run(speed_mps: float = 1.0, rate_hz: float = 15.0, n: int = 30):
    """(t_s (n,), T_world_from_cam (n, 4, 4)) of a camera moving along +x."""
    t = np.arange(n) / rate_hz
    T = np.repeat(np.eye(4)[None], n, axis=0)
    T[:, 0, 3] = speed_mps * t
    return t, T


def _rot_z(angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_recorded_truth_is_the_pose_one_clock_offset_later():
    t, T = _straight_run()
    errors = replace(IndoorErrors.none(), truth_time_offset_s=(0.02, 0.02))
    shifts = set()
    for seed in range(8):
        rec = recorded_truth(T, t, errors, np.eye(4), np.random.default_rng(seed))
        shift = rec[:, 0, 3] - T[:, 0, 3]
        assert np.allclose(shift, shift[0], atol=1e-9)  # the same offset every frame
        shifts.add(round(float(shift[0]), 6))
    assert shifts == {-0.02, 0.02}  # 20 ms at 1 m/s, either clock ahead
    exact = recorded_truth(T, t, IndoorErrors.none(), np.eye(4), np.random.default_rng(0))
    assert np.allclose(exact, T)


def test_poses_at_interpolates_rotation_and_extends_the_ends():
    T = np.repeat(np.eye(4)[None], 2, axis=0)
    T[1, :3, :3] = _rot_z(0.2)
    T[1, 0, 3] = 1.0
    out = poses_at(T, np.array([0.0, 1.0]), np.array([0.5, 1.5]))
    assert np.allclose(out[0, :3, :3], _rot_z(0.1))
    assert out[0, 0, 3] == pytest.approx(0.5)
    assert np.allclose(out[1, :3, :3], _rot_z(0.3))
    assert out[1, 0, 3] == pytest.approx(1.5)


def test_the_hand_eye_residual_has_the_configured_size_and_reaches_the_record():
    errors = IndoorErrors.none()
    errors = replace(errors, hand_eye_translation_m=0.01, hand_eye_rotation_rad=math.radians(1))
    E = hand_eye_residual(errors, np.random.default_rng(3))
    angle = math.acos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1))
    assert angle == pytest.approx(math.radians(1.0), rel=1e-6)
    assert np.linalg.norm(E[:3, 3]) == pytest.approx(0.01, rel=1e-6)
    t, T = _straight_run()
    rec = recorded_truth(T, t, errors, E, np.random.default_rng(0))
    for i in (0, 10, 29):
        assert np.allclose(np.linalg.inv(T[i]) @ rec[i], E, atol=1e-12)


def test_the_loop_worlds_mapping_poses_carry_the_rig_residual():
    from monoloc.sim.closed_loop_world import IndoorLoopWorld

    world = IndoorLoopWorld("small", seed=0)
    E = world.T_cam_from_recorded
    assert np.linalg.norm(E[:3, 3]) == pytest.approx(0.01, rel=1e-6)
    t, T = _straight_run()
    rec = world.tracker_poses(T, np.random.default_rng(1), t)
    # the tracker's jitter (1 mm, 0.05 deg), its bias (3 mm) and 1-3 cm of clock offset
    # along +x on top of the residual: sideways (y) and in height the residual shows
    rel = np.stack([np.linalg.inv(T[i] @ E) @ rec[i] for i in range(len(T))])
    assert np.median(np.abs(rel[:, 2, 3])) < 0.004
    lag = np.median(rec[:, 0, 3] - (T @ E)[:, 0, 3])
    assert 0.008 < abs(lag) < 0.035
    # calibrated intrinsics differ from the rendering ones
    k, kc = world.intrinsics, world.calibrated_intrinsics
    assert abs(kc.fx / k.fx - 1) == pytest.approx(0.007, rel=1e-6)
    assert math.hypot(kc.cx - k.cx, kc.cy - k.cy) == pytest.approx(2.0, rel=1e-6)
    # without sensor noise the record is the truth
    exact = IndoorLoopWorld("small", seed=0, sensor_noise=False)
    assert np.allclose(exact.tracker_poses(T, np.random.default_rng(1), t), T)


def test_calibrated_intrinsics_are_off_by_the_configured_amounts():
    errors = replace(IndoorErrors.none(), intrinsics_focal_error=0.01, intrinsics_principal_px=3)
    k = calibrated_intrinsics(D435_COLOR, errors, np.random.default_rng(0))
    assert abs(k.fx / D435_COLOR.fx - 1) == pytest.approx(0.01)
    assert k.fy / D435_COLOR.fy == pytest.approx(k.fx / D435_COLOR.fx)
    assert math.hypot(k.cx - 320.0, k.cy - 240.0) == pytest.approx(3.0)
    assert calibrated_intrinsics(D435_COLOR, IndoorErrors.none(), np.random.default_rng(0)) == (
        D435_COLOR
    )


def test_rolling_shutter_shifts_the_top_and_bottom_rows_opposite_ways():
    k = D435_COLOR
    h, w = k.height_px, k.width_px
    ramp = np.broadcast_to(np.arange(w, dtype=np.float32)[None, :], (h, w)).copy()
    depth = np.full((h, w), 2.0, np.float32)
    T = np.eye(4)  # the camera turned about its y axis (a yaw) by 0.05 rad since last frame
    c, s = math.cos(0.05), math.sin(0.05)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    out = rolling_shutter(ramp, depth, T, k, 0.4)
    centre = slice(w // 2 - 20, w // 2 + 20)
    top = float(np.mean(out[0, centre] - ramp[0, centre]))
    mid = float(np.mean(out[h // 2, centre] - ramp[h // 2, centre]))
    bottom = float(np.mean(out[-1, centre] - ramp[-1, centre]))
    expected = k.fx * math.tan(0.05 * 0.4)  # the whole readout's image motion
    assert abs(bottom - top) == pytest.approx(expected, rel=0.05)
    assert top * bottom < 0  # read before and after the frame's time
    assert abs(mid) < 0.05 * expected
    assert np.array_equal(rolling_shutter(ramp, depth, T, k, 0.0), ramp)


def test_the_closed_loop_is_judged_against_the_recorded_truth():
    from monoloc.sim.closed_loop import LoopConfig, LoopResult
    from monoloc.sim.closed_loop_record import localization_error_m, true_localization_error_m

    n = 5
    truth = np.column_stack([np.arange(n, dtype=float), np.zeros(n), np.zeros(n)])
    recorded = truth + [0.03, 0.0, 0.0]
    result = LoopResult(
        LoopConfig(),
        {"t_s": np.arange(n) / 15.0, "truth_cam": truth, "recorded_cam": recorded},
        truth.copy(),
        {},
        0.3,
        0.0,
    )
    assert np.allclose(localization_error_m(result), 0.03)
    assert np.allclose(true_localization_error_m(result), 0.0)
    del result.frames["recorded_cam"]
    assert np.allclose(localization_error_m(result), 0.0)


def test_a_recorded_mapping_lap_carries_the_rigs_calibration(tmp_path):
    """The run folder a mapping lap uploads: camera.json with the calibrated intrinsics,
    groundtruth.txt with the recorded (offset, residual) poses, not the sim's truth."""
    from types import SimpleNamespace

    from monoloc.core.formats import tum
    from monoloc.sim.closed_loop import LoopConfig
    from monoloc.sim.closed_loop_record import TumRecorder
    from monoloc.sim.closed_loop_world import IndoorLoopWorld

    world = IndoorLoopWorld("small", seed=0)
    recorder = TumRecorder(tmp_path / "map", world, "test")
    t, T = _straight_run(n=8)
    image = np.zeros((world.intrinsics.height_px, world.intrinsics.width_px), np.uint8)
    for i in range(len(t)):
        recorder(i, float(t[i]), image, None, T[i])
    signals = np.tile([1.0, 0.0], (len(t), 1))
    recorder.finish(SimpleNamespace(config=LoopConfig(seed=0), frames={"signals": signals}))
    _, camera = tum.read_camera_json(tmp_path / "map")
    assert camera["fx"] == pytest.approx(world.calibrated_intrinsics.fx)
    assert camera["fx"] != pytest.approx(world.intrinsics.fx)
    gt = tum.read_ground_truth(tmp_path / "map" / "groundtruth.txt")
    # the residual's 1 deg turns every recorded orientation (the tracker's jitter: 0.05 deg)
    for row, T_true in zip(gt, T, strict=True):
        R_rec = _quat_xyzw_to_R(row[4:8])
        angle = math.acos(np.clip((np.trace(T_true[:3, :3].T @ R_rec) - 1) / 2, -1, 1))
        assert math.degrees(angle) == pytest.approx(1.0, abs=0.2)


def _quat_xyzw_to_R(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )

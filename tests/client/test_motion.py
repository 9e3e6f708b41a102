"""The motion model's integration of the arc: exact at any step size, with or without a
lever arm, and on a straight line; per-particle noise around it; the lever arm's fit."""

from __future__ import annotations

import math

import numpy as np
import pytest

from monoloc.client.motion import MotionConfig, advance, fit_lever_arm_m, predict
from monoloc.core.errors import InvalidInputError

SPEED_MPS, YAW_RATE_RADPS, DT_S = 9.0, 0.47, 0.1


def _circle(t_s: np.ndarray, lever_arm_m: float = 0.0) -> np.ndarray:
    """Camera poses (n, 3) at times t_s of an axle driving a left circle from the origin
    heading +X at SPEED_MPS and YAW_RATE_RADPS, the camera lever_arm_m ahead of it."""
    radius = SPEED_MPS / YAW_RATE_RADPS
    yaw = YAW_RATE_RADPS * t_s
    x = radius * np.sin(yaw) + lever_arm_m * np.cos(yaw)
    y = radius * (1.0 - np.cos(yaw)) + lever_arm_m * np.sin(yaw)
    return np.stack([x, y, np.arctan2(np.sin(yaw), np.cos(yaw))], axis=1)


@pytest.mark.parametrize("lever_arm_m", [0.0, 1.3])
def test_exact_integration_stays_on_the_circle_at_10_hz(lever_arm_m):
    n = 60  # 6 s: more than a quarter turn
    truth = _circle(np.arange(n) * DT_S, lever_arm_m)
    pose = truth[:1].copy()
    for k in range(1, n):
        pose = advance(pose, SPEED_MPS, YAW_RATE_RADPS, DT_S, lever_arm_m)
        np.testing.assert_allclose(pose[0], truth[k], atol=1e-9)


def test_a_straight_line_handles_zero_yaw_rate_and_ignores_the_lever_arm():
    start = np.array([[3.0, -2.0, 0.4]])
    moved = advance(start, 5.0, 0.0, 2.0, 0.7)[0]
    np.testing.assert_allclose(moved, [3 + 10 * math.cos(0.4), -2 + 10 * math.sin(0.4), 0.4])


def test_predict_draws_noise_per_particle_around_the_exact_arc():
    rng = np.random.default_rng(3)
    cfg = MotionConfig(speed_noise_mps=(-0.2, 0.2), yaw_rate_noise_radps=(-0.05, 0.05))
    start = np.zeros((4000, 3))
    moved = predict(start, SPEED_MPS, YAW_RATE_RADPS, DT_S, cfg, rng)
    exact = advance(start[:1], SPEED_MPS, YAW_RATE_RADPS, DT_S)[0]
    np.testing.assert_allclose(moved.mean(axis=0), exact, atol=2e-3)
    assert moved[:, 2].std() > 1e-3


def test_the_lever_arm_is_fitted_from_poses_and_measured_speed():
    rng = np.random.default_rng(5)
    # a drive with left and right turns of varying yaw rate, camera 1.3 m ahead
    n = 400
    rates = 0.4 * np.sin(np.arange(n) * 0.03)
    speeds = 7.0 + np.sin(np.arange(n) * 0.01)
    poses = [np.array([0.0, 0.0, 0.5])]
    for k in range(n - 1):
        # the truth integrates finely (10 sub-steps), the signals are sampled at frames
        pose = poses[-1][None]
        for s in np.linspace(0, 1, 10, endpoint=False):
            rate = np.interp(k + s, np.arange(n), rates)
            speed = np.interp(k + s, np.arange(n), speeds)
            pose = advance(pose, speed, rate, DT_S / 10, 1.3)
        poses.append(pose[0])
    poses = np.array(poses)
    times = np.arange(n) * DT_S
    noisy = poses + rng.normal(0, [0.003, 0.003, 0.0002], size=poses.shape)
    measured = speeds * 1.01 + rng.normal(0, 0.05, n)  # 1 % scale error and noise
    assert fit_lever_arm_m(noisy, times, measured) == pytest.approx(1.3, abs=0.1)
    assert fit_lever_arm_m(poses, times, speeds) == pytest.approx(1.3, abs=0.01)
    straight = np.stack([np.arange(n) * 0.7, np.zeros(n), np.zeros(n)], axis=1)
    with pytest.raises(InvalidInputError, match="too little to fit"):
        fit_lever_arm_m(straight, times, np.full(n, 7.0))

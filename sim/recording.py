"""The errors a real recording carries. The world is rendered from the true values; the
files carry the measured ones.

``RecordingErrors()`` is realistic and the default; ``RecordingErrors.none()`` makes the
written geometry exact (tests that check geometry use it).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from monoloc.sim.vehicle import _rpy


@dataclass(frozen=True)
class RecordingErrors:
    """Each error is off when its size is 0 (or the flag False).

    lidar_motion_distortion: columns fire over the sweep while the car moves, points
    not compensated. calib_translation_m / calib_rotation_rad: size of the error of the
    written LiDAR-to-camera calibration. pose_error_m / pose_yaw_error_rad: standard
    deviation of the slowly varying (time constant pose_error_time_s) error of written
    poses (GNSS/INS-like). speed_*, yaw_rate_*: vehicle signal errors (scale factor,
    bias, white noise). exposure_bias_ev: standard deviation of a run's exposure offset;
    sensor_noise: camera shot/read noise on or off.
    """

    lidar_motion_distortion: bool = True
    calib_translation_m: float = 0.01
    calib_rotation_rad: float = math.radians(0.1)
    pose_error_m: float = 0.03
    pose_vertical_error_m: float = 0.02
    pose_yaw_error_rad: float = math.radians(0.05)
    pose_error_time_s: float = 20.0
    speed_scale_error: float = 0.01
    speed_bias_mps: float = 0.02
    speed_noise_mps: float = 0.05
    yaw_rate_bias_radps: float = 0.002
    yaw_rate_noise_radps: float = 0.005
    exposure_bias_ev: float = 0.3
    sensor_noise: bool = True

    @classmethod
    def none(cls) -> RecordingErrors:
        """Exact geometry and signals (camera noise off too)."""
        return cls(
            lidar_motion_distortion=False,
            calib_translation_m=0.0,
            calib_rotation_rad=0.0,
            pose_error_m=0.0,
            pose_vertical_error_m=0.0,
            pose_yaw_error_rad=0.0,
            speed_scale_error=0.0,
            speed_bias_mps=0.0,
            speed_noise_mps=0.0,
            yaw_rate_bias_radps=0.0,
            yaw_rate_noise_radps=0.0,
            exposure_bias_ev=0.0,
            sensor_noise=False,
        )

    def to_dict(self) -> dict:
        return asdict(self)


def perturb_calibration(
    T_cam_from_lidar: np.ndarray, errors: RecordingErrors, rng: np.random.Generator
) -> np.ndarray:
    """The calibration a recording would write: the true one off by a random
    translation of norm ``calib_translation_m`` and rotation of ``calib_rotation_rad``."""
    direction = rng.standard_normal(3)
    direction /= np.linalg.norm(direction)
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    angle = errors.calib_rotation_rad
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R_err = np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K
    T = np.eye(4)
    T[:3, :3] = R_err @ T_cam_from_lidar[:3, :3]
    T[:3, 3] = T_cam_from_lidar[:3, 3] + errors.calib_translation_m * direction
    return T


def smooth_random(
    times_s: np.ndarray, sigma: float, time_constant_s: float, rng: np.random.Generator
) -> np.ndarray:
    """(n,) zero-mean Gauss-Markov process of standard deviation ``sigma`` sampled at
    ``times_s`` (first-order, correlation time ``time_constant_s``)."""
    n = len(times_s)
    out = np.zeros(n)
    if sigma <= 0 or n == 0:
        return out
    out[0] = sigma * rng.standard_normal()
    for k in range(1, n):
        a = math.exp(-(times_s[k] - times_s[k - 1]) / time_constant_s)
        out[k] = a * out[k - 1] + sigma * math.sqrt(1 - a * a) * rng.standard_normal()
    return out


def apply_pose_errors(
    T_world_from_cam: np.ndarray,
    times_s: np.ndarray,
    errors: RecordingErrors,
    rng: np.random.Generator,
) -> np.ndarray:
    """(n, 4, 4) written poses: the true ones (n, 4, 4) with slowly varying horizontal and
    vertical position offsets and a small heading error (about the camera's own centre)."""
    tau = errors.pose_error_time_s
    ex = smooth_random(times_s, errors.pose_error_m / math.sqrt(2), tau, rng)
    ey = smooth_random(times_s, errors.pose_error_m / math.sqrt(2), tau, rng)
    ez = smooth_random(times_s, errors.pose_vertical_error_m, tau, rng)
    eyaw = smooth_random(times_s, errors.pose_yaw_error_rad, tau, rng)
    out = np.array(T_world_from_cam, dtype=np.float64, copy=True)
    out[:, :3, :3] = _rpy(np.zeros_like(eyaw), np.zeros_like(eyaw), eyaw) @ out[:, :3, :3]
    out[:, 0, 3] += ex
    out[:, 1, 3] += ey
    out[:, 2, 3] += ez
    return out


def measured_signals(
    speed_mps: np.ndarray,
    yaw_rate_radps: np.ndarray,
    errors: RecordingErrors,
    rng: np.random.Generator,
):
    """(speed, yaw_rate) as the car's sensors report them: scale error, bias, noise."""
    scale = 1.0 + errors.speed_scale_error * rng.standard_normal()
    speed = speed_mps * scale + errors.speed_bias_mps * rng.standard_normal()
    speed = speed + errors.speed_noise_mps * rng.standard_normal(len(speed_mps))
    bias = errors.yaw_rate_bias_radps * rng.standard_normal()
    yaw_rate = (
        yaw_rate_radps
        + bias
        + errors.yaw_rate_noise_radps * rng.standard_normal(len(yaw_rate_radps))
    )
    return np.maximum(speed, 0.0), yaw_rate

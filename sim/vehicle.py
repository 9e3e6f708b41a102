"""The vehicle: kinematic bicycle model driven by a pure-pursuit steering controller and a
speed controller along a path, and its sensor rig.

The vehicle frame has its origin on the ground below the rear axle, x forward, y left,
z up; the bicycle model's speed is the rear axle's. Body pitch follows longitudinal
acceleration and roll follows lateral acceleration (a soft suspension), so camera poses
are 6-DoF like real ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import R_world_from_cam_level, invert_rigid
from monoloc.sim.path import Path


@dataclass(frozen=True)
class VehicleConfig:
    """Vehicle, controller and speed profile. Speeds m/s, accelerations m/s^2."""

    wheelbase_m: float = 2.7
    speed_range_mps: tuple[float, float] = (6.0, 14.0)
    max_lateral_accel: float = 2.0
    max_accel: float = 1.2
    max_decel: float = 2.0
    max_steer_rad: float = 0.6
    max_steer_rate_radps: float = 0.8
    lookahead_time_s: float = 0.8
    min_lookahead_m: float = 4.0
    dt_s: float = 0.01
    steer_disturbance_rad: float = 0.0
    steer_disturbance_period_s: float = 4.0
    pitch_per_accel_rad: float = 0.004
    roll_per_lateral_accel_rad: float = 0.006


@dataclass(frozen=True)
class SensorRig:
    """Where the sensors sit on the vehicle (KITTI-like). The camera looks along the
    vehicle's x axis; the LiDAR is behind and above it, with a small mounting rotation
    (roll, pitch, yaw in rad) so that the LiDAR-to-camera transform is not trivial."""

    camera_ahead_of_rear_axle_m: float = 1.0
    camera_height_m: float = 1.65
    lidar_behind_camera_m: float = 0.27
    lidar_above_camera_m: float = 0.08
    lidar_left_of_camera_m: float = -0.004
    lidar_mount_rpy_rad: tuple[float, float, float] = (0.004, -0.006, 0.008)
    stereo_baseline_m: float = 0.5371657  # KITTI's: camera 1 sits this far right of camera 0

    def T_vehicle_from_cam(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = R_world_from_cam_level(0.0)
        T[:3, 3] = [self.camera_ahead_of_rear_axle_m, 0.0, self.camera_height_m]
        return T

    def T_vehicle_from_cam1(self) -> np.ndarray:
        """The right camera of the stereo pair: camera 0 moved ``stereo_baseline_m`` along
        its own +x (a rectified pair, like KITTI's gray cameras 0 and 1)."""
        T_cam0_from_cam1 = np.eye(4)
        T_cam0_from_cam1[0, 3] = self.stereo_baseline_m
        return self.T_vehicle_from_cam() @ T_cam0_from_cam1

    def T_vehicle_from_lidar(self) -> np.ndarray:
        roll, pitch, yaw = self.lidar_mount_rpy_rad
        T = np.eye(4)
        T[:3, :3] = _rpy(roll, pitch, yaw)
        T[:3, 3] = [
            self.camera_ahead_of_rear_axle_m - self.lidar_behind_camera_m,
            self.lidar_left_of_camera_m,
            self.camera_height_m + self.lidar_above_camera_m,
        ]
        return T

    def T_cam_from_lidar(self) -> np.ndarray:
        """KITTI's ``Tr`` (velodyne to camera 0), true value."""
        return invert_rigid(self.T_vehicle_from_cam()) @ self.T_vehicle_from_lidar()


def _rpy(roll, pitch, yaw) -> np.ndarray:
    """Rotation Rz(yaw) Ry(pitch) Rx(roll); scalars give (3, 3), arrays (n,) give (n, 3, 3)."""
    roll, pitch, yaw = np.broadcast_arrays(
        *(np.asarray(a, dtype=np.float64) for a in (roll, pitch, yaw))
    )
    cr, sr, cp, sp, cy, sy = (
        np.cos(roll),
        np.sin(roll),
        np.cos(pitch),
        np.sin(pitch),
        np.cos(yaw),
        np.sin(yaw),
    )
    R = np.stack(
        [
            np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], axis=-1),
            np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], axis=-1),
            np.stack([-sp, cp * sr, cp * cr], axis=-1),
        ],
        axis=-2,
    )
    return R


@dataclass(frozen=True)
class VehicleStates:
    """True states at the integration rate: t_s, x_m, y_m, yaw_rad (unwrapped),
    speed_mps (rear axle), yaw_rate_radps, pitch_rad, roll_rad; all (M,)."""

    t_s: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray
    speed_mps: np.ndarray
    yaw_rate_radps: np.ndarray
    pitch_rad: np.ndarray
    roll_rad: np.ndarray

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1])

    def sample(self, times_s: np.ndarray) -> dict[str, np.ndarray]:
        """All states linearly interpolated at ``times_s`` (n,)."""
        times_s = np.asarray(times_s, dtype=np.float64)
        return {
            name: np.interp(times_s, self.t_s, getattr(self, name))
            for name in (
                "x_m",
                "y_m",
                "yaw_rad",
                "speed_mps",
                "yaw_rate_radps",
                "pitch_rad",
                "roll_rad",
            )
        }

    def T_world_from_vehicle(self, times_s: np.ndarray) -> np.ndarray:
        """(n, 4, 4) vehicle poses at ``times_s`` (z-up world)."""
        st = self.sample(np.atleast_1d(times_s))
        n = len(st["x_m"])
        T = np.zeros((n, 4, 4))
        T[:, :3, :3] = _rpy(st["roll_rad"], st["pitch_rad"], st["yaw_rad"])
        T[:, 0, 3] = st["x_m"]
        T[:, 1, 3] = st["y_m"]
        T[:, 3, 3] = 1.0
        return T


def speed_profile(path: Path, config: VehicleConfig, rng: np.random.Generator) -> np.ndarray:
    """(N,) target speed along ``path``: a random cruising speed per straight stretch,
    limited in curves by the lateral acceleration, with feasible braking/acceleration."""
    s = path.s_m
    cruise = np.empty_like(s)
    turning = np.abs(path.curvature) > 0.02
    starts = np.flatnonzero(np.diff(turning.astype(int)) != 0) + 1
    bounds = np.concatenate([[0], starts, [len(s)]])
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        cruise[a:b] = rng.uniform(*config.speed_range_mps)
    curve_limit = np.sqrt(config.max_lateral_accel / np.maximum(np.abs(path.curvature), 1e-6))
    v = np.minimum(cruise, curve_limit)
    ds = np.diff(s, prepend=s[0])
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2 * config.max_decel * ds[i + 1]))
    for i in range(1, len(v)):
        v[i] = min(v[i], math.sqrt(v[i - 1] ** 2 + 2 * config.max_accel * ds[i]))
    return v


def drive(
    path: Path,
    config: VehicleConfig,
    rng: np.random.Generator,
    max_duration_s: float | None = None,
    target: Path | None = None,
) -> VehicleStates:
    """Drive along ``target`` (default ``path``) with the speed profile of ``path``
    until its end (or ``max_duration_s``). Returns true states every ``dt_s``."""
    target = target or path
    if len(target.s_m) < 8:
        raise InvalidInputError(f"path too short to drive ({target.length_m:.1f} m)")
    v_ref = speed_profile(path, config, rng)
    v_ref_on_target = np.interp(target.s_m / target.length_m * path.length_m, path.s_m, v_ref)
    dt, L = config.dt_s, config.wheelbase_m
    x, y = target.xy[0]
    yaw = target.heading_rad[0]
    v = float(v_ref_on_target[0])
    steer = 0.0
    idx = 0
    out = []
    t = 0.0
    phase = rng.uniform(0, 2 * np.pi)
    n_pts = len(target.s_m)
    while True:
        # Nearest path point, searched forward from the last one.
        window = target.xy[idx : min(n_pts, idx + 200)]
        idx += int(np.argmin(np.sum((window - (x, y)) ** 2, axis=1)))
        if idx >= n_pts - 2 or (max_duration_s is not None and t > max_duration_s):
            break
        lookahead = max(config.min_lookahead_m, config.lookahead_time_s * v)
        j = min(n_pts - 1, idx + int(lookahead / (target.s_m[1] - target.s_m[0])))
        dx, dy = target.xy[j, 0] - x, target.xy[j, 1] - y
        alpha = math.atan2(dy, dx) - yaw
        dist = max(math.hypot(dx, dy), 1e-3)
        wanted = math.atan2(2.0 * L * math.sin(alpha), dist)
        wanted += config.steer_disturbance_rad * math.sin(
            2 * np.pi * t / config.steer_disturbance_period_s + phase
        )
        wanted = float(np.clip(wanted, -config.max_steer_rad, config.max_steer_rad))
        max_step = config.max_steer_rate_radps * dt
        steer += float(np.clip(wanted - steer, -max_step, max_step))
        accel = float(
            np.clip(2.0 * (v_ref_on_target[idx] - v), -config.max_decel, config.max_accel)
        )
        yaw_rate = v * math.tan(steer) / L
        out.append((t, x, y, yaw, v, yaw_rate, accel))
        x += v * math.cos(yaw) * dt
        y += v * math.sin(yaw) * dt
        yaw += yaw_rate * dt
        v = max(0.0, v + accel * dt)
        t += dt
    arr = np.array(out)
    accel = _lowpass(arr[:, 6], 0.3 / dt)
    lateral = _lowpass(arr[:, 4] * arr[:, 5], 0.3 / dt)
    return VehicleStates(
        t_s=arr[:, 0],
        x_m=arr[:, 1],
        y_m=arr[:, 2],
        yaw_rad=arr[:, 3],
        speed_mps=arr[:, 4],
        yaw_rate_radps=arr[:, 5],
        pitch_rad=-config.pitch_per_accel_rad * accel,
        roll_rad=config.roll_per_lateral_accel_rad * lateral,
    )


def _lowpass(x: np.ndarray, samples: float) -> np.ndarray:
    """First-order low-pass (time constant in samples), run forward."""
    a = 1.0 / max(samples, 1.0)
    out = np.empty_like(x)
    acc = x[0]
    for i, xi in enumerate(x):
        acc += a * (xi - acc)
        out[i] = acc
    return out

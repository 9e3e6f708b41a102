"""Kinematic motion model of docs/method.md section 8, per-particle noise.

Each step integrates the arc exactly (constant speed and yaw rate over the step): the
paper's Euler step, along the heading at the start of the step, misses the arc by about
V dt * gamma dt / 2 to the outside of every turn (2 cm at 9 m/s, 0.47 rad/s and 10 Hz).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import wrap_angle
from monoloc.core.mounting import CameraMounting, PlanarMount


@dataclass(frozen=True)
class MotionConfig:
    """Bounds of the uniform noise added to the measured signals, per particle and step.

    speed_noise_mps: (v_lo, v_hi) of w_v; yaw_rate_noise_radps: (g_lo, g_hi) of w_gamma.
    """

    speed_noise_mps: tuple[float, float] = (-0.5, 0.5)
    yaw_rate_noise_radps: tuple[float, float] = (-0.1, 0.1)
    # How far ahead of the point whose speed is measured (e.g. the rear axle) the camera
    # sits, along the heading. 0 is docs/method.md's model; with a lever arm l the camera also
    # moves sideways at gamma * l, which matters in turns (a 90-degree turn with l = 1 m
    # displaces the camera 1.4 m more than the plain model says).
    lever_arm_m: float = 0.0
    # The camera's whole mounting (T_vehicle_from_cam, monoloc.core.mounting): its planar
    # part (lever arm, lateral offset, yaw offset) moves the camera with the reference
    # point. Given, it replaces ``lever_arm_m`` (which must then be 0 or the same).
    mounting: CameraMounting | None = None

    def __post_init__(self) -> None:
        if (
            self.mounting is not None
            and self.lever_arm_m != 0.0
            and self.lever_arm_m != self.mounting.lever_arm_m
        ):
            raise InvalidInputError(
                f"lever_arm_m {self.lever_arm_m} and the mounting's lever arm "
                f"{self.mounting.lever_arm_m} differ: give one"
            )

    @property
    def mount(self) -> PlanarMount:
        """The camera's planar pose in the vehicle frame the motion model moves it by."""
        if self.mounting is not None:
            return self.mounting.planar
        return PlanarMount(x_m=self.lever_arm_m)


def advance(
    poses_world: np.ndarray,
    speed_mps: np.ndarray | float,
    yaw_rate_radps: np.ndarray | float,
    dt_s: float,
    mount: PlanarMount | float = 0.0,
) -> np.ndarray:
    """Camera poses (P, 3) (X, Y, psi) moved by one step of the given speed and yaw rate
    (scalars or (P,)) of the vehicle's reference point, the camera sitting at ``mount``
    in the vehicle frame (a float: a lever arm, the camera that far ahead of the point,
    looking along the heading); a new (P, 3) array.

    The point drives the arc of constant speed and yaw rate along its heading
    psi_v = psi - mount.yaw_rad, a chord of length V dt sinc(gamma dt / 2) in the
    direction psi_v + gamma dt / 2, and the camera stays at ``mount`` in the vehicle's
    frame: it moves by that chord plus (R(psi_v') - R(psi_v)) (x_m, y_m).
    """
    if not isinstance(mount, PlanarMount):
        mount = PlanarMount(x_m=float(mount))
    psi = poses_world[:, 2]
    psi_v = psi - mount.yaw_rad
    turn = np.asarray(yaw_rate_radps, dtype=np.float64) * dt_s
    distance = np.asarray(speed_mps, dtype=np.float64) * dt_s
    out = np.empty_like(poses_world)
    # np.sinc(x) = sin(pi x) / (pi x): exact and stable as the yaw rate goes to 0.
    chord = distance * np.sinc(turn / (2.0 * np.pi))
    mid = psi_v + 0.5 * turn
    new_psi_v = psi_v + turn
    out[:, 0] = poses_world[:, 0] + chord * np.cos(mid)
    out[:, 1] = poses_world[:, 1] + chord * np.sin(mid)
    if mount.x_m or mount.y_m:
        dc, ds = np.cos(new_psi_v) - np.cos(psi_v), np.sin(new_psi_v) - np.sin(psi_v)
        out[:, 0] += mount.x_m * dc - mount.y_m * ds
        out[:, 1] += mount.x_m * ds + mount.y_m * dc
    out[:, 2] = wrap_angle(psi + turn)
    return out


def predict(
    particles: np.ndarray,
    speed_mps: float,
    yaw_rate_radps: float,
    dt_s: float,
    config: MotionConfig,
    rng: np.random.Generator,
) -> np.ndarray:
    """One step of every particle. particles (P, 3) (X, Y, psi) -> new (P, 3) array.

    Each particle draws its own speed and yaw-rate noise: V_hat = V + w_v,
    gamma_hat = gamma + w_gamma, then moves by :func:`advance`.
    """
    n = len(particles)
    speed = speed_mps + rng.uniform(*config.speed_noise_mps, size=n)
    yaw_rate = yaw_rate_radps + rng.uniform(*config.yaw_rate_noise_radps, size=n)
    return advance(particles, speed, yaw_rate, dt_s, config.mount)


def _recorded_steps(
    poses_world: np.ndarray, timestamps_s: np.ndarray, speed_mps: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A recorded run's poses (N, 3), timestamps (N,), speeds (N,) as float arrays, and
    the (N-1,) mask of consecutive frames both of which are finite (the steps to fit on).
    Raises InvalidInputError when the shapes do not match."""
    poses = np.asarray(poses_world, dtype=np.float64)
    t = np.asarray(timestamps_s, dtype=np.float64)
    v = np.asarray(speed_mps, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != 3 or len(t) != len(poses) or len(v) != len(poses):
        raise InvalidInputError(
            f"need poses (N, 3), timestamps (N,) and speeds (N,), got {poses.shape}, "
            f"{t.shape}, {v.shape}"
        )
    ok = np.all(np.isfinite(poses), axis=1) & np.isfinite(t) & np.isfinite(v)
    return poses, t, v, ok[:-1] & ok[1:]


def fit_lever_arm_m(
    poses_world: np.ndarray,
    timestamps_s: np.ndarray,
    speed_mps: np.ndarray,
    min_turn_rad: float = 0.5,
) -> float:
    """The camera's distance ahead of the speed reference point, fitted by least squares
    on a run with camera poses (N, 3), their timestamps (N,) and the measured speed (N,)
    (e.g. the training run): between consecutive frames the camera moves by the exact arc
    of the reference point (speed from the signal, heading change from the poses) plus
    l (u(psi') - u(psi)), u the unit heading vector; l is the only unknown. Without a
    lever arm, the model puts the camera to the outside of every turn.

    Raises InvalidInputError when the run turns by less than ``min_turn_rad`` in total
    (nothing to fit on) or the inputs do not match.
    """
    poses, t, v, pair = _recorded_steps(poses_world, timestamps_s, speed_mps)
    dt = np.diff(t)[pair]
    psi0, psi1 = poses[:-1, 2][pair], poses[1:, 2][pair]
    turn = wrap_angle(psi1 - psi0)
    if np.abs(turn).sum() < min_turn_rad:
        raise InvalidInputError(
            f"the run turns by {np.abs(turn).sum():.2f} rad in all: too little to fit a lever arm"
        )
    distance = 0.5 * (v[:-1] + v[1:])[pair] * dt
    chord = distance * np.sinc(turn / (2.0 * np.pi))
    mid = psi0 + 0.5 * turn
    moved = poses[1:, :2][pair] - poses[:-1, :2][pair]
    residual = moved - chord[:, None] * np.stack([np.cos(mid), np.sin(mid)], axis=1)
    design = np.stack([np.cos(psi1) - np.cos(psi0), np.sin(psi1) - np.sin(psi0)], axis=1)
    return float(np.sum(design * residual) / np.sum(design * design))


def fit_mount(
    poses_world: np.ndarray,
    timestamps_s: np.ndarray,
    speed_mps: np.ndarray,
    min_turn_rad: float = 0.5,
    max_yaw_rad: float = 0.5,
) -> PlanarMount:
    """The camera's planar mounting (lever arm, lateral offset, yaw offset) fitted by
    least squares on a run with camera poses (N, 3), their timestamps (N,) and the
    measured speed of the vehicle's reference point (N,): between consecutive frames the
    camera moves as :func:`advance` says (the point's exact arc along the heading
    psi - yaw, heading change from the poses) plus (R(psi_v') - R(psi_v)) (x, y). For a
    given yaw offset the lever arm and lateral offset are linear; the yaw offset (within
    ``max_yaw_rad``) minimises the residual. The yaw offset shows in the direction the
    camera travels; the offsets need turns.

    Raises InvalidInputError when the run turns by less than ``min_turn_rad`` in total
    or the inputs do not match.
    """
    poses, t, v, pair = _recorded_steps(poses_world, timestamps_s, speed_mps)
    psi0, psi1 = poses[:-1, 2][pair], poses[1:, 2][pair]
    turn = wrap_angle(psi1 - psi0)
    if np.abs(turn).sum() < min_turn_rad:
        raise InvalidInputError(
            f"the run turns by {np.abs(turn).sum():.2f} rad in all: too little to fit a "
            "camera mounting on"
        )
    chord = 0.5 * (v[:-1] + v[1:])[pair] * np.diff(t)[pair] * np.sinc(turn / (2.0 * np.pi))
    moved = (poses[1:, :2][pair] - poses[:-1, :2][pair]).ravel()

    def solve(yaw: float) -> tuple[float, np.ndarray]:
        a0, a1 = psi0 - yaw, psi1 - yaw
        mid = a0 + 0.5 * turn
        along = np.stack([chord * np.cos(mid), chord * np.sin(mid)], axis=1).ravel()
        dc, ds = np.cos(a1) - np.cos(a0), np.sin(a1) - np.sin(a0)
        design = np.stack(
            [np.stack([dc, ds], axis=1).ravel(), np.stack([-ds, dc], axis=1).ravel()], axis=1
        )
        residual = moved - along
        offsets, *_ = np.linalg.lstsq(design, residual, rcond=None)
        return float(np.sum((residual - design @ offsets) ** 2)), offsets

    grid = np.linspace(-max_yaw_rad, max_yaw_rad, 201)
    costs = [solve(float(y))[0] for y in grid]
    best = int(np.argmin(costs))
    lo, hi = grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]
    golden = (math.sqrt(5.0) - 1.0) / 2.0
    for _ in range(60):  # golden-section search in the grid cell around the best
        a, b = hi - golden * (hi - lo), lo + golden * (hi - lo)
        if solve(a)[0] < solve(b)[0]:
            hi = b
        else:
            lo = a
    yaw = 0.5 * (lo + hi)
    _, (x_m, y_m) = solve(yaw)
    return PlanarMount(float(x_m), float(y_m), float(yaw))

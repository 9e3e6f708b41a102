"""Kinematic motion model of docs/method.md section 8, per-particle noise.

Each step integrates the arc exactly (constant speed and yaw rate over the step): the
paper's Euler step, along the heading at the start of the step, misses the arc by about
V dt * gamma dt / 2 to the outside of every turn (2 cm at 9 m/s, 0.47 rad/s and 10 Hz).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import wrap_angle


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


def advance(
    poses_world: np.ndarray,
    speed_mps: np.ndarray | float,
    yaw_rate_radps: np.ndarray | float,
    dt_s: float,
    lever_arm_m: float = 0.0,
) -> np.ndarray:
    """Camera poses (P, 3) (X, Y, psi) moved by one step of the given speed and yaw rate
    (scalars or (P,)) of the point ``lever_arm_m`` behind the camera; a new (P, 3) array.

    That point drives the arc of constant speed and yaw rate, a chord of length
    V dt sinc(gamma dt / 2) in the direction psi + gamma dt / 2, and the camera stays
    ``lever_arm_m`` ahead of it along the new heading.
    """
    psi = poses_world[:, 2]
    turn = np.asarray(yaw_rate_radps, dtype=np.float64) * dt_s
    distance = np.asarray(speed_mps, dtype=np.float64) * dt_s
    out = np.empty_like(poses_world)
    # np.sinc(x) = sin(pi x) / (pi x): exact and stable as the yaw rate goes to 0.
    chord = distance * np.sinc(turn / (2.0 * np.pi))
    mid = psi + 0.5 * turn
    new_psi = psi + turn
    out[:, 0] = poses_world[:, 0] + chord * np.cos(mid)
    out[:, 1] = poses_world[:, 1] + chord * np.sin(mid)
    if lever_arm_m:
        out[:, 0] += lever_arm_m * (np.cos(new_psi) - np.cos(psi))
        out[:, 1] += lever_arm_m * (np.sin(new_psi) - np.sin(psi))
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
    return advance(particles, speed, yaw_rate, dt_s, config.lever_arm_m)


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
    poses = np.asarray(poses_world, dtype=np.float64)
    t = np.asarray(timestamps_s, dtype=np.float64)
    v = np.asarray(speed_mps, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != 3 or len(t) != len(poses) or len(v) != len(poses):
        raise InvalidInputError(
            f"need poses (N, 3), timestamps (N,) and speeds (N,), got {poses.shape}, "
            f"{t.shape}, {v.shape}"
        )
    ok = np.all(np.isfinite(poses), axis=1) & np.isfinite(t) & np.isfinite(v)
    pair = ok[:-1] & ok[1:]
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

"""Kinematic motion model of METHOD.md section 8 (with sin for Y), per-particle noise."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monoloc.core.geometry import wrap_angle


@dataclass(frozen=True)
class MotionConfig:
    """Bounds of the uniform noise added to the measured signals, per particle and step.

    speed_noise_mps: (v_lo, v_hi) of w_v; yaw_rate_noise_radps: (g_lo, g_hi) of w_gamma.
    """

    speed_noise_mps: tuple[float, float] = (-0.5, 0.5)
    yaw_rate_noise_radps: tuple[float, float] = (-0.1, 0.1)
    # How far ahead of the point whose speed is measured (e.g. the rear axle) the camera
    # sits, along the heading. 0 is METHOD.md's model; with a lever arm l the camera also
    # moves sideways at gamma * l, which matters in turns (a 90-degree turn with l = 1 m
    # displaces the camera 1.4 m more than the plain model says).
    lever_arm_m: float = 0.0


def predict(
    particles: np.ndarray,
    speed_mps: float,
    yaw_rate_radps: float,
    dt_s: float,
    config: MotionConfig,
    rng: np.random.Generator,
) -> np.ndarray:
    """One Euler step of every particle. particles (P, 3) (X, Y, psi) -> new (P, 3) array.

    Each particle draws its own speed and yaw-rate noise: V_hat = V + w_v,
    gamma_hat = gamma + w_gamma, then X += V_hat cos(psi) dt, Y += V_hat sin(psi) dt,
    psi += gamma_hat dt.
    """
    n = len(particles)
    speed = speed_mps + rng.uniform(*config.speed_noise_mps, size=n)
    yaw_rate = yaw_rate_radps + rng.uniform(*config.yaw_rate_noise_radps, size=n)
    out = np.empty_like(particles)
    psi = particles[:, 2]
    cos_psi, sin_psi = np.cos(psi), np.sin(psi)
    out[:, 0] = particles[:, 0] + speed * cos_psi * dt_s
    out[:, 1] = particles[:, 1] + speed * sin_psi * dt_s
    if config.lever_arm_m:
        sideways = yaw_rate * config.lever_arm_m * dt_s
        out[:, 0] -= sideways * sin_psi
        out[:, 1] += sideways * cos_psi
    out[:, 2] = wrap_angle(psi + yaw_rate * dt_s)
    return out

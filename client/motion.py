"""Kinematic motion model of METHOD.md section 8 (with sin for Y), per-particle noise."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from client.geometry import wrap_angle


@dataclass(frozen=True)
class MotionConfig:
    """Bounds of the uniform noise added to the measured signals, per particle and step.

    speed_noise_mps: (v_lo, v_hi) of w_v; yaw_rate_noise_radps: (g_lo, g_hi) of w_gamma.
    """

    speed_noise_mps: tuple[float, float] = (-0.5, 0.5)
    yaw_rate_noise_radps: tuple[float, float] = (-0.1, 0.1)


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
    out[:, 0] = particles[:, 0] + speed * np.cos(psi) * dt_s
    out[:, 1] = particles[:, 1] + speed * np.sin(psi) * dt_s
    out[:, 2] = wrap_angle(psi + yaw_rate * dt_s)
    return out

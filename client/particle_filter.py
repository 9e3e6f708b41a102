"""Particle filter on the planar pose (X, Y, psi): METHOD.md sections 7 and 8.

Predict with measured speed and yaw rate, update with the Gaussian-mixture measurement
model, systematic resampling when the effective sample size falls, and recovery by
re-seeding around the current hypotheses when every particle has been unlikely for
several frames. All randomness comes from the injected ``np.random.Generator``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from monoloc.client.motion import MotionConfig, predict
from monoloc.client.resampling import (
    effective_sample_size,
    normalise_log_weights,
    systematic_resample,
)
from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import circular_mean, wrap_angle
from monoloc.core.measurement import Hypotheses, MeasurementModel, log_likelihood_and_distance


@dataclass(frozen=True)
class FilterConfig:
    """Settings of the particle filter (METHOD.md sections 7-8)."""

    n_particles: int = 1000
    motion: MotionConfig = field(default_factory=MotionConfig)
    resample_ess_fraction: float = 0.5
    init_position_std_m: float = 0.5
    init_yaw_std_rad: float = math.radians(2.0)
    # A frame with hypotheses is "unlikely" when the smallest squared Mahalanobis distance
    # (under Sigma1) between any particle and any bias-corrected hypothesis exceeds this
    # (chi-square, 3 dof: P(> 25) = 1.5e-5). An unlikely frame still updates the weights,
    # except the ``lost_after_frames``-th in a row, which re-seeds the particles around its
    # own hypotheses instead. ``lost`` holds from the first unlikely frame until a likely
    # one or the re-seed; frames without hypotheses leave the count alone.
    lost_mahalanobis_sq: float = 25.0
    # The reported pose is the main mode: particles within this radius of the weighted
    # median position (the covariance, used for the retrieval prior, covers all of them).
    mode_radius_m: float = 3.0
    lost_after_frames: int = 3
    # Roughening after resampling: Gaussian jitter (m, m, rad) so that a cloud that
    # collapsed onto a few particles can still move to where the measurements are.
    roughening_std: tuple[float, float, float] = (0.02, 0.02, math.radians(0.1))


@dataclass(frozen=True)
class FilterEstimate:
    """Weighted mean pose (X, Y, psi) with its (3, 3) covariance, and filter health."""

    pose_world: np.ndarray
    covariance: np.ndarray
    effective_sample_size: float
    n_hypotheses: int
    lost: bool

    @property
    def position_std_m(self) -> float:
        """Square root of the largest eigenvalue of the position covariance."""
        return float(math.sqrt(max(np.linalg.eigvalsh(self.covariance[:2, :2]).max(), 0.0)))


def weighted_estimate(particles: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean (3,) with circular mean heading, and covariance (3, 3) about it."""
    mean = np.empty(3)
    mean[:2] = weights @ particles[:, :2]
    mean[2] = circular_mean(particles[:, 2], weights)
    residuals = particles - mean
    residuals[:, 2] = wrap_angle(residuals[:, 2])
    cov = (residuals * weights[:, None]).T @ residuals
    return mean, cov


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    order = np.argsort(values)
    cumulative = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])


def mode_estimate(particles: np.ndarray, weights: np.ndarray, radius_m: float) -> np.ndarray:
    """Pose (3,) of the main mode: the weighted mean of the particles within ``radius_m``
    of the weighted median position. With one mode this is the weighted mean; when a few
    particles still sit on wrong hypotheses (right after initialisation) it ignores them
    instead of averaging across tens of metres."""
    centre = np.array(
        [_weighted_median(particles[:, 0], weights), _weighted_median(particles[:, 1], weights)]
    )
    near = np.hypot(particles[:, 0] - centre[0], particles[:, 1] - centre[1]) <= radius_m
    if weights[near].sum() <= 0.0:
        near = np.ones(len(particles), dtype=bool)
    w = weights[near] / weights[near].sum()
    mean, _ = weighted_estimate(particles[near], w)
    return mean


def sample_around(
    centres: np.ndarray,
    n: int,
    position_std_m: float,
    yaw_std_rad: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """n particles (n, 3) spread evenly over centres (C, 3) with Gaussian noise."""
    picks = np.arange(n) % len(centres)
    noise = rng.normal(size=(n, 3)) * [position_std_m, position_std_m, yaw_std_rad]
    particles = centres[picks] + noise
    particles[:, 2] = wrap_angle(particles[:, 2])
    return particles


class ParticleFilter:
    """The on-vehicle filter. Not thread-safe; one per vehicle."""

    def __init__(
        self, config: FilterConfig, model: MeasurementModel, rng: np.random.Generator
    ) -> None:
        if config.n_particles < 1:
            raise InvalidInputError("n_particles must be >= 1")
        self.config = config
        self.model = model
        self.rng = rng
        self.particles: np.ndarray | None = None
        self.log_weights = np.zeros(config.n_particles)
        self._unlikely_frames = 0

    @property
    def initialised(self) -> bool:
        return self.particles is not None

    def initialise(self, pose_world: np.ndarray, position_std_m: float, yaw_std_rad: float) -> None:
        """Start from a prior: a pose (3,) or several (C, 3), spread by the given stds."""
        centres = np.atleast_2d(np.asarray(pose_world, dtype=np.float64))
        self.particles = sample_around(
            centres, self.config.n_particles, position_std_m, yaw_std_rad, self.rng
        )
        self.log_weights = np.zeros(self.config.n_particles)
        self._unlikely_frames = 0

    def initialise_from_hypotheses(self, hypotheses: Hypotheses) -> None:
        """Start around the (bias-corrected) hypotheses of one frame."""
        if len(hypotheses) == 0:
            raise InvalidInputError("cannot initialise from an empty set of hypotheses")
        centres = hypotheses.pose_world + self.model.mu1
        self.initialise(centres, self.config.init_position_std_m, self.config.init_yaw_std_rad)
        # Weigh the seeded particles by the same frame: where several hypotheses agree the
        # mixture is denser, so a lone wrong hypothesis loses its share at once.
        self.update(hypotheses)

    def predict(self, dt_s: float, speed_mps: float, yaw_rate_radps: float) -> None:
        if self.particles is None:
            return
        self.particles = predict(
            self.particles, speed_mps, yaw_rate_radps, dt_s, self.config.motion, self.rng
        )

    def update(self, hypotheses: Hypotheses) -> None:
        """Weigh the particles by the mixture; no hypotheses means no update."""
        if self.particles is None or len(hypotheses) == 0:
            return
        log_lik, closest = log_likelihood_and_distance(self.particles, hypotheses, self.model)
        if closest > self.config.lost_mahalanobis_sq:
            self._unlikely_frames += 1
            if self._unlikely_frames >= self.config.lost_after_frames:
                self.initialise_from_hypotheses(hypotheses)
                return
        else:
            self._unlikely_frames = 0
        self.log_weights = self.log_weights + log_lik
        weights = normalise_log_weights(self.log_weights)
        ess = effective_sample_size(weights)
        if ess < self.config.resample_ess_fraction * self.config.n_particles:
            idx = systematic_resample(weights, self.rng)
            jitter = self.rng.normal(size=self.particles.shape) * self.config.roughening_std
            self.particles = self.particles[idx] + jitter
            self.particles[:, 2] = wrap_angle(self.particles[:, 2])
            self.log_weights = np.zeros(self.config.n_particles)
        else:
            self.log_weights = np.log(weights)

    def step(
        self,
        dt_s: float,
        speed_mps: float,
        yaw_rate_radps: float,
        hypotheses: Hypotheses | None = None,
    ) -> FilterEstimate | None:
        """One frame: predict by ``dt_s`` with the speed and yaw rate measured since the
        previous frame, then update with this frame's hypotheses (none: prediction only);
        returns the estimate.

        Uninitialised, there is nothing to predict: the first frame with hypotheses
        initialises the filter around them (and is weighed by them), and until then the
        result is None.
        """
        hypotheses = hypotheses if hypotheses is not None else Hypotheses.empty()
        if self.particles is None:
            if len(hypotheses) == 0:
                return None
            self.initialise_from_hypotheses(hypotheses)
        else:
            self.predict(dt_s, speed_mps, yaw_rate_radps)
            self.update(hypotheses)
        return self.estimate(n_hypotheses=len(hypotheses))

    @property
    def lost(self) -> bool:
        return self._unlikely_frames > 0

    def estimate(self, n_hypotheses: int = 0) -> FilterEstimate:
        if self.particles is None:
            raise InvalidInputError("the filter is not initialised")
        weights = normalise_log_weights(self.log_weights)
        _, cov = weighted_estimate(self.particles, weights)
        return FilterEstimate(
            pose_world=mode_estimate(self.particles, weights, self.config.mode_radius_m),
            covariance=cov,
            effective_sample_size=effective_sample_size(weights),
            n_hypotheses=n_hypotheses,
            lost=self.lost,
        )

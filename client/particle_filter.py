"""Particle filter on the planar pose (X, Y, psi): docs/method.md sections 7 and 8.

Predict with measured speed and yaw rate, update with the Gaussian-mixture measurement
model, systematic resampling when the effective sample size falls. Recovery: a frame
whose hypotheses all lie far from every particle is "unlikely"; the filter re-seeds
around such a frame's hypotheses only when they agree with the hypotheses of several
recent frames once those are carried forward by the vehicle's own measured motion (a
re-seed candidate must be consistent with the dead-reckoned motion), never on a few
frames that contradict it, and only when more frames agree with it than agreed with the
filter's own track among the recent frames with hypotheses (``track_support``: support
from before a silence counts, so a place found elsewhere after it must outweigh it; for a
place farther than the dead reckoning since the last support can have drifted, however
long the silence).
``frames_since_support`` (frames since the hypotheses last agreed with the particles)
tells the vehicle's loop to widen the retrieval prior and then to search the whole map.
A candidate whose heading contradicts the filter's (``FilterConfig.reseed_turn_rad``)
must also outweigh every likely frame of the last ``track_memory_frames``. All
randomness comes from the injected ``np.random.Generator``.

The reported pose (``estimate().pose_world``) is that of a Gaussian filter riding on the
particles' main mode (``client/refine.py``, ``FilterConfig.refine``); the mode itself is
``estimate().mode_world``, and the reported pose with ``refine=None``.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from monoloc.client.motion import MotionConfig, advance, predict
from monoloc.client.refine import ModeRefiner, RefineConfig
from monoloc.client.resampling import (
    effective_sample_size,
    normalise_log_weights,
    systematic_resample,
)
from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import circular_mean, wrap_angle
from monoloc.core.measurement import Hypotheses, MeasurementModel, log_likelihood_and_distance


@dataclass(frozen=True)
class GuardConfig:
    """The innovation check on the particles' mode (``ParticleFilter`` guard).

    A frame's own estimate is its joint pose, else its hypothesis with the most inliers,
    with the measurement model's covariance for it (``hypothesis_gaussians``). It is
    confident when that covariance's position spread sqrt(var X + var Y) is at most
    ``max_spread_m`` and the server flagged no poorly pinned pose in the frame (no
    "alternative" hypothesis: a moved car carries every entry the same wrong way). When
    ``frames`` confident frames in a row put the pose more than ``min_offset_m`` and
    ``mahalanobis_sq`` (under the estimate's covariance plus ``min_mode_std_m`` of the
    mode's own error) from the mode, at most ``max_offset_m`` away
    (farther is the re-seed rule's to judge: an aliased street), and agree with each
    other (moved by the measured motion, within ``agree_m`` plus the odometry's drift
    ``FilterConfig.drift_per_m`` since, and ``agree_rad``), the
    particles move to the last of them. Why: a measurement model calibrated on another
    street can weigh every hypothesis of a street under the outlier floor; the particles
    then dead-reckon away from poses the server gets right on every frame."""

    frames: int = 3
    max_spread_m: float = 0.06
    min_offset_m: float = 0.15
    max_offset_m: float = 3.0
    mahalanobis_sq: float = 16.0
    min_mode_std_m: float = 0.02
    agree_m: float = 0.1
    agree_rad: float = math.radians(1.0)

    def __post_init__(self) -> None:
        if self.frames < 2:
            raise InvalidInputError(f"GuardConfig.frames must be >= 2: {self}")
        positive = (
            self.max_spread_m,
            self.min_offset_m,
            self.max_offset_m,
            self.mahalanobis_sq,
            self.min_mode_std_m,
            self.agree_m,
            self.agree_rad,
        )
        if min(positive) <= 0 or self.max_offset_m <= self.min_offset_m:
            raise InvalidInputError(f"GuardConfig bounds must be positive and ordered: {self}")


@dataclass(frozen=True)
class FilterConfig:
    """Settings of the particle filter (docs/method.md sections 7-8)."""

    n_particles: int = 1000
    motion: MotionConfig = field(default_factory=MotionConfig)
    resample_ess_fraction: float = 0.5
    init_position_std_m: float = 0.5
    init_yaw_std_rad: float = math.radians(2.0)
    # A frame with hypotheses is "unlikely" when the smallest squared Mahalanobis distance
    # (under Sigma1; with the "pnp" model under the hypothesis's own covariance or Sigma1,
    # whichever is nearer) between any particle and any bias-corrected hypothesis exceeds this
    # (chi-square, 3 dof: P(> 25) = 1.5e-5). An unlikely frame still updates the weights
    # (the mixture's outlier floor keeps them nearly flat), unless it re-seeds. ``lost``
    # holds from the first unlikely frame until a likely one or a re-seed; frames without
    # hypotheses leave it alone.
    lost_mahalanobis_sq: float = 25.0
    # The reported pose is the main mode: particles within this radius of the weighted
    # median position (the covariance, used for the retrieval prior, covers all of them).
    mode_radius_m: float = 3.0
    # Re-seeding: an unlikely frame re-seeds around one of its hypotheses when hypotheses
    # of at least ``reseed_min_frames`` frames (this one included) among the last
    # ``reseed_window_frames`` agree with it within the tolerances once moved to this
    # frame by the measured speed and yaw rate. 4 frames at 10 Hz: 0.4 s of evidence
    # that moves like the car; the window (2 s) bounds the odometry drift (~0.2 m with
    # a 1 % speed scale error at 9 m/s). A candidate within the tolerances of the filter's
    # own estimate re-seeds only after ``reseed_min_frames`` unlikely frames in a row
    # (see ``reseed_candidate``).
    # Initialisation: the first frame in which at least ``init_min_agreeing`` hypotheses
    # agree within the re-seed tolerances starts the filter (around all of that frame's
    # hypotheses, weighed by it); a frame with a lone hypothesis does not, unless the
    # hypotheses of ``reseed_min_frames`` frames agree once moved by the measured motion
    # (the re-seed rule). A lone PnP pose is sometimes off by metres (night frames, few
    # inliers), and a filter started there takes several frames to leave it. 1: the
    # first frame with any hypothesis starts the filter.
    init_min_agreeing: int = 2
    reseed_min_frames: int = 4
    # A re-seed must also outweigh the filter's own track: its candidate needs more
    # agreeing frames than the track has likely frames among the last
    # ``reseed_window_frames`` frames that had hypotheses (the frames that contradict it
    # included), counting only likely frames of the last ``track_memory_frames`` frames.
    # A track that was supported until hypotheses stopped coming keeps that support
    # through the silence: what retrieval finds elsewhere afterwards (an aliased street
    # that moves like the car) has to agree with the car's motion for more frames than
    # the track had, instead of four. The memory bounds how long: 10 s of dead reckoning
    # (~0.9 m at 9 m/s with a 1 % speed scale error). A filter started or re-seeded
    # without support (a kidnapped start) has none to outweigh.
    track_memory_frames: int = 100
    # ... unless the candidate lies farther from the filter's estimate than the dead
    # reckoning since the last likely frame can have drifted: ``reseed_position_tol_m``
    # plus this fraction of the distance driven since (2 %: a 1 % speed scale error and
    # the gyro's drift). Such a candidate says the track is wrong, not that it drifted,
    # and the track's support does not age: it must be outweighed by frames that
    # contradict the track (each pushes one of its frames out of the last
    # ``reseed_window_frames`` with hypotheses: 11 of them against a fully supported
    # track). Without it, a few frames of a look-alike street far away, found after a
    # silence, take the filter there for good.
    drift_per_m: float = 0.02
    # A candidate whose heading differs from the filter's by more than this contradicts
    # the gyro, not just the position: its frames do not displace the track's support
    # (every likely frame of the last ``track_memory_frames`` counts, up to
    # ``reseed_window_frames``). A street that looks like the car's but runs another way
    # (recurring facades found by the whole-map search after a silence) then cannot take
    # a filter that was well supported in the last 10 s, however many frames it fills;
    # one heading the car's way (the same street further on) can, as above.
    reseed_turn_rad: float = math.radians(20.0)
    reseed_window_frames: int = 20
    reseed_position_tol_m: float = 1.0
    reseed_yaw_tol_rad: float = math.radians(3.0)
    # Roughening after resampling: Gaussian jitter (along m, across m, rad) so that a cloud that
    # collapsed onto a few particles can still move to where the measurements are.
    roughening_std: tuple[float, float, float] = (0.02, 0.02, math.radians(0.1))
    # The reported pose: a Gaussian filter riding on the main mode (client/refine.py)
    # averages the hypotheses over time with the measured motion and the speed signal's
    # scale; None reports the particles' mode itself (docs/method.md's filter).
    refine: RefineConfig | None = field(default_factory=RefineConfig)
    # Never worse than the frame's own estimate for long (GuardConfig).
    guard: GuardConfig = field(default_factory=GuardConfig)


@dataclass(frozen=True)
class FilterEstimate:
    """Weighted mean pose (X, Y, psi) with its (3, 3) covariance, and filter health."""

    pose_world: np.ndarray
    covariance: np.ndarray
    effective_sample_size: float
    n_hypotheses: int
    lost: bool
    frames_since_support: int = 0
    # the particles' main mode (3,): pose_world when the refinement is off
    mode_world: np.ndarray | None = None

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


def along_across_to_world(offsets: np.ndarray, heading_rad: np.ndarray) -> np.ndarray:
    """Offsets (n, 3) (along m, across m, yaw rad) of poses heading ``heading_rad`` (n,)
    in world axes (X m, Y m, yaw rad)."""
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    out = offsets.copy()
    out[:, 0] = c * offsets[:, 0] - s * offsets[:, 1]
    out[:, 1] = s * offsets[:, 0] + c * offsets[:, 1]
    return out


def sample_around(
    centres: np.ndarray,
    n: int,
    position_std_m: float,
    yaw_std_rad: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """n particles (n, 3) spread evenly over centres (C, 3) with Gaussian noise (drawn
    along and across each centre's heading: the same particles, turned, in a turned world
    frame)."""
    picks = np.arange(n) % len(centres)
    noise = rng.normal(size=(n, 3)) * [position_std_m, position_std_m, yaw_std_rad]
    particles = centres[picks] + along_across_to_world(noise, centres[picks, 2])
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
        # Frames since the hypotheses last agreed with the particles (0 right after a
        # likely frame or a (re-)seed); frames without hypotheses count too.
        self.frames_since_support = 0
        self.n_reseeds = 0
        # The bias-corrected hypotheses of recent frames (M, 3), each moved to the current
        # frame with the measured signals (noise-free), and the frame each came from (M,):
        # the re-seed's evidence.
        self._recent_world = np.zeros((0, 3))
        self._recent_frame = np.zeros(0, dtype=np.int64)
        self._frame = 0
        # The last ``reseed_window_frames`` frames with hypotheses since the filter was
        # (re-)seeded, as (frame, likely): the track's support (see ``track_support``).
        self._track_log: deque[tuple[int, bool]] = deque(maxlen=config.reseed_window_frames)
        # Every likely frame of the last ``track_memory_frames`` since the last (re-)seed.
        self._likely_frames: deque[int] = deque(maxlen=max(1, config.track_memory_frames))
        # Distance driven (m) since the last likely frame or (re-)seed: what the dead
        # reckoning can have drifted over (``FilterConfig.drift_per_m``).
        self.driven_since_support_m = 0.0
        self.refiner = ModeRefiner(config.refine) if config.refine is not None else None
        self._refiner_disagreeing = 0  # consecutive frames the refiner and the mode disagree
        # The guard's evidence: confident frame estimates (K, 3) that disagreed with the
        # mode in a row, each moved to the current frame by the measured motion.
        self._guard_world = np.zeros((0, 3))
        self._guard_driven_m = np.zeros(0)  # distance driven since each was seen
        self.n_guard_moves = 0

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
        self.frames_since_support = 0
        self._track_log.clear()
        self._likely_frames.clear()
        self.driven_since_support_m = 0.0
        if self.refiner is not None:
            self.refiner.stop()  # it starts again from the new particles' mode

    def initialise_from_hypotheses(self, hypotheses: Hypotheses) -> None:
        """Start around the (bias-corrected) hypotheses of one frame."""
        if len(hypotheses) == 0:
            raise InvalidInputError("cannot initialise from an empty set of hypotheses")
        centres = self.model.corrected(hypotheses)
        self.initialise(centres, self.config.init_position_std_m, self.config.init_yaw_std_rad)
        # Weigh the seeded particles by the same frame: where several hypotheses agree the
        # mixture is denser, so a lone wrong hypothesis loses its share at once.
        self.update(hypotheses)

    def predict(self, dt_s: float, speed_mps: float, yaw_rate_radps: float) -> None:
        """Move the particles (and the remembered hypotheses, kept before initialisation
        too) by one step of the measured speed and yaw rate."""
        motion = self.config.motion
        if self.particles is not None:
            self.particles = predict(
                self.particles, speed_mps, yaw_rate_radps, dt_s, motion, self.rng
            )
            self.driven_since_support_m += abs(float(speed_mps)) * float(dt_s)
            if self.refiner is not None:
                self.refiner.predict(dt_s, speed_mps, yaw_rate_radps, motion.mount)
        if len(self._recent_world):
            self._recent_world = advance(
                self._recent_world, speed_mps, yaw_rate_radps, dt_s, motion.mount
            )
        if len(self._guard_world):
            self._guard_world = advance(
                self._guard_world, speed_mps, yaw_rate_radps, dt_s, motion.mount
            )
            self._guard_driven_m = self._guard_driven_m + abs(float(speed_mps)) * float(dt_s)

    def update(self, hypotheses: Hypotheses) -> None:
        """Weigh the particles by the mixture; no hypotheses means no update. An unlikely
        frame with a motion-consistent re-seed candidate re-seeds instead."""
        if self.particles is None:
            return
        if len(hypotheses) == 0:
            self.frames_since_support += 1
            self._remember(np.zeros((0, 3)))
            return
        log_lik, closest = log_likelihood_and_distance(self.particles, hypotheses, self.model)
        centres = self.model.corrected(hypotheses)
        if closest > self.config.lost_mahalanobis_sq:
            self._unlikely_frames += 1
            self.frames_since_support += 1
            self._track_log.append((self._frame, False))
            chosen = self.reseed_candidate(centres)
            self._remember(centres)
            if chosen is not None:
                self._reseed(hypotheses, chosen)
                return
        else:
            self._unlikely_frames = 0
            self.frames_since_support = 0
            self.driven_since_support_m = 0.0
            self._track_log.append((self._frame, True))
            self._likely_frames.append(self._frame)
            self._remember(centres)
        self._weigh(log_lik)

    @property
    def track_support(self) -> int:
        """Likely frames among the last ``reseed_window_frames`` frames with hypotheses
        since the last (re-)seed, within ``track_memory_frames`` of this frame."""
        oldest = self._frame - self.config.track_memory_frames
        return sum(1 for frame, likely in self._track_log if likely and frame > oldest)

    @property
    def drift_bound_m(self) -> float:
        """How far the dead reckoning since the last likely frame can have taken the
        filter's estimate from the truth (``FilterConfig.drift_per_m``)."""
        cfg = self.config
        return cfg.reseed_position_tol_m + cfg.drift_per_m * self.driven_since_support_m

    def support_against(self, candidate_world: np.ndarray) -> int:
        """The track's support a re-seed onto ``candidate_world`` (3,) must outweigh:
        ``track_support``, or, for a candidate beyond ``drift_bound_m`` of the filter's
        estimate, the likely frames among the last ``reseed_window_frames`` frames with
        hypotheses however old."""
        mode = self._mode()
        if float(np.hypot(*(candidate_world[:2] - mode[:2]))) <= self.drift_bound_m:
            return self.track_support
        return sum(1 for _, likely in self._track_log if likely)

    @property
    def held_support(self) -> int:
        """Likely frames of the last ``track_memory_frames`` since the last (re-)seed, up
        to ``reseed_window_frames``: the support a candidate that contradicts the
        filter's heading must outweigh."""
        oldest = self._frame - self.config.track_memory_frames
        held = sum(1 for frame in self._likely_frames if frame > oldest)
        return min(held, self.config.reseed_window_frames)

    def _remember(self, centres_world: np.ndarray) -> None:
        """Keep this frame's hypotheses (H, 3) and forget those that left the window."""
        keep = self._recent_frame > self._frame - self.config.reseed_window_frames + 1
        self._recent_world = np.concatenate([self._recent_world[keep], centres_world])
        self._recent_frame = np.concatenate(
            [self._recent_frame[keep], np.full(len(centres_world), self._frame)]
        )
        self._frame += 1

    def reseed_candidate(self, centres_world: np.ndarray) -> np.ndarray | None:
        """Indices of this frame's (bias-corrected) hypotheses (H, 3) to re-seed around,
        or None: the hypothesis agreed with by the most recent frames (moved here by the
        measured motion; a past hypothesis nearer the filter's estimate than the candidate
        does not count), with its neighbours in this frame, if at least
        ``reseed_min_frames`` frames (this one included) agree. Near the filter's own
        estimate (within the re-seed tolerances) only after ``reseed_min_frames``
        unlikely frames in a row: before that the agreeing frames may be ones that agreed
        with the filter, and the candidate is an outlier, not a place to move to."""
        cfg = self.config
        if not len(centres_world):
            return None
        support = np.ones(len(centres_world), dtype=np.int64)
        if len(self._recent_world):
            # distinct past frames with a hypothesis that agrees, per hypothesis of this one
            agree = _agrees(centres_world, self._recent_world, cfg)
            if self.particles is not None:
                # A past hypothesis nearer the filter's estimate than the candidate is the
                # track's evidence, not the candidate's: else, within the 1 m tolerance, the
                # right frames before a few wrong ones decimetres off count for them.
                mode = self._mode()
                to_mode = np.hypot(*(self._recent_world[:, :2] - mode[:2]).T)
                offsets = centres_world[:, None, :2] - self._recent_world[None, :, :2]
                agree &= np.hypot(offsets[..., 0], offsets[..., 1]) < to_mode[None, :]
            frames = np.where(agree, self._recent_frame[None, :], -1)
            for row, picked in enumerate(frames):
                support[row] += len(np.unique(picked[picked >= 0]))
        near = _agrees(centres_world, centres_world, cfg)
        # most frames first, then the most hypotheses of this frame around it
        best = int(np.lexsort((-near.sum(axis=1), -support))[0])
        if support[best] < cfg.reseed_min_frames:
            return None
        if self.particles is not None:
            # the track has had more frames agree with it than the candidate has
            if support[best] <= self.support_against(centres_world[best]):
                return None
            turn = abs(float(wrap_angle(centres_world[best, 2] - self._mode()[2])))
            if turn > cfg.reseed_turn_rad and support[best] <= self.held_support:
                return None
        chosen = np.flatnonzero(near[best])
        if (
            self.particles is not None
            and self._unlikely_frames < cfg.reseed_min_frames
            and _agrees(centres_world[chosen], self._mode()[None], cfg).any()
        ):
            # Within the tolerances of where the filter already is, the past frames may
            # "agree" with the candidate only because they agreed with the filter: a lone
            # outlier of a tight Sigma1 (a night hypothesis 0.5-0.8 m off) after likely
            # frames is weighed like any other frame, not jumped to. A filter locked a
            # little off still re-seeds once ``reseed_min_frames`` frames in a row have
            # contradicted it.
            return None
        return chosen

    def _mode(self) -> np.ndarray:
        """The reported pose (3,): the particles' main mode."""
        weights = normalise_log_weights(self.log_weights)
        return mode_estimate(self.particles, weights, self.config.mode_radius_m)

    def _reseed(self, hypotheses: Hypotheses, chosen: np.ndarray) -> None:
        """Particles around the chosen hypotheses, weighed by the whole frame."""
        centres = self.model.corrected(hypotheses)[chosen]
        self.initialise(centres, self.config.init_position_std_m, self.config.init_yaw_std_rad)
        self.n_reseeds += 1
        # the frames that agreed with the candidate are the new track's support
        agree = _agrees(centres, self._recent_world, self.config).any(axis=0)
        frames = sorted({int(f) for f in self._recent_frame[agree]})
        self._track_log.extend((frame, True) for frame in frames)
        self._likely_frames.extend(frames)
        log_lik, _ = log_likelihood_and_distance(self.particles, hypotheses, self.model)
        self._weigh(log_lik)

    def _weigh(self, log_lik: np.ndarray) -> None:
        """Add the frame's log likelihoods (P,) to the weights; resample when the
        effective sample size falls."""
        self.log_weights = self.log_weights + log_lik
        weights = normalise_log_weights(self.log_weights)
        ess = effective_sample_size(weights)
        if ess < self.config.resample_ess_fraction * self.config.n_particles:
            idx = systematic_resample(weights, self.rng)
            jitter = self.rng.normal(size=self.particles.shape) * self.config.roughening_std
            kept = self.particles[idx]
            self.particles = kept + along_across_to_world(jitter, kept[:, 2])
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

        Uninitialised, only the remembered hypotheses move: the first frame whose
        hypotheses may start the filter (``FilterConfig.init_min_agreeing``) initialises
        it around them (and weighs it by them), and until then the result is None.
        """
        hypotheses = hypotheses if hypotheses is not None else Hypotheses.empty()
        if self.particles is None:
            self.predict(dt_s, speed_mps, yaw_rate_radps)  # the remembered hypotheses only
            if not self._start(hypotheses):
                return None
        else:
            self.predict(dt_s, speed_mps, yaw_rate_radps)
            reseeds = self.n_reseeds
            self.update(hypotheses)
            if self.n_reseeds == reseeds:
                self._guard(hypotheses)
        self._refine(hypotheses)
        return self.estimate(n_hypotheses=len(hypotheses))

    def _guard(self, hypotheses: Hypotheses) -> None:
        """The innovation check on the mode (``GuardConfig``): after ``frames`` confident,
        mutually consistent frame estimates in a row that the mode contradicts, move the
        particles to the last one (and the refinement with them)."""
        cfg = self.config.guard
        own = _frame_estimate(hypotheses, self.model, cfg)
        if own is None:
            self._guard_reset()
            return
        pose, cov = own
        mode = self._mode()
        floor = np.diag([cfg.min_mode_std_m**2, cfg.min_mode_std_m**2, 0.0])
        diff = pose - mode
        diff[2] = wrap_angle(diff[2])
        offset_m = math.hypot(diff[0], diff[1])
        try:
            squared = float(diff @ np.linalg.solve(cov + floor, diff))
        except np.linalg.LinAlgError:
            squared = 0.0
        if not (cfg.min_offset_m < offset_m <= cfg.max_offset_m and squared > cfg.mahalanobis_sq):
            self._guard_reset()
            return
        if len(self._guard_world):
            # the odometry may have drifted since each was seen (FilterConfig.drift_per_m)
            apart = self._guard_world - pose
            tolerance_m = cfg.agree_m + self.config.drift_per_m * self._guard_driven_m
            consistent = bool(
                np.all(np.hypot(apart[:, 0], apart[:, 1]) <= tolerance_m)
                and np.all(np.abs(wrap_angle(apart[:, 2])) <= cfg.agree_rad)
            )
            if not consistent:
                self._guard_reset()
        self._guard_world = np.vstack([self._guard_world, pose])
        self._guard_driven_m = np.append(self._guard_driven_m, 0.0)
        if len(self._guard_world) < cfg.frames:
            return
        # move the cloud to the frame's estimate, keeping the track's history (this is
        # the same place, measured better than the mode holds it)
        self.particles = sample_around(
            pose[None],
            self.config.n_particles,
            max(cfg.min_offset_m / 3.0, math.sqrt(cov[0, 0] + cov[1, 1])),
            max(math.radians(0.2), math.sqrt(cov[2, 2])),
            self.rng,
        )
        self.log_weights = np.zeros(self.config.n_particles)
        log_lik, _ = log_likelihood_and_distance(self.particles, hypotheses, self.model)
        self._weigh(log_lik)
        if self.refiner is not None:
            self.refiner.stop()
        self._guard_reset()
        self.n_guard_moves += 1

    def _guard_reset(self) -> None:
        self._guard_world = np.zeros((0, 3))
        self._guard_driven_m = np.zeros(0)

    def _refine(self, hypotheses: Hypotheses) -> None:
        """Correct the mode's Gaussian filter with this frame's hypotheses; (re)start it
        from the particles' mode and spread when it is not running or no longer agrees
        with that mode (``RefineConfig``: at once beyond the tolerances; beyond the
        Mahalanobis distance under both spreads, once that has lasted
        ``restart_after_frames`` frames in a row, the frames before corrected as usual; a
        restarting frame is already in the particles)."""
        if self.refiner is None:
            return
        mode = self._mode()
        _, cov = weighted_estimate(self.particles, normalise_log_weights(self.log_weights))
        corrected = False
        if self.refiner.active and self.refiner.agrees_with(mode, cov):
            self.refiner.correct(hypotheses, self.model)
            corrected = True
            if self.refiner.agrees_with(mode, cov):
                self._refiner_disagreeing = 0
                return
        patience = self.refiner.config.restart_after_frames
        if self.refiner.active and patience > 1 and self.refiner.within_tolerances(mode):
            self._refiner_disagreeing += 1
            if self._refiner_disagreeing < patience:
                if not corrected:
                    self.refiner.correct(hypotheses, self.model)
                return
        self._refiner_disagreeing = 0
        self.refiner.start(mode, cov)

    def _start(self, hypotheses: Hypotheses) -> bool:
        """Initialise on this frame if its hypotheses may start the filter (see
        ``FilterConfig.init_min_agreeing``); otherwise remember them. Whether it started."""
        centres = self.model.corrected(hypotheses)
        if len(hypotheses) == 0:
            self._remember(centres)
            return False
        agreeing = _agrees(centres, centres, self.config).sum(axis=1)
        if agreeing.max() >= self.config.init_min_agreeing:
            self.initialise_from_hypotheses(hypotheses)  # its update remembers the frame
            return True
        chosen = self.reseed_candidate(centres)
        self._remember(centres)
        if chosen is None:
            return False
        self.initialise(
            centres[chosen], self.config.init_position_std_m, self.config.init_yaw_std_rad
        )
        log_lik, _ = log_likelihood_and_distance(self.particles, hypotheses, self.model)
        self._weigh(log_lik)
        return True

    @property
    def lost(self) -> bool:
        return self._unlikely_frames > 0

    def estimate(self, n_hypotheses: int = 0) -> FilterEstimate:
        """The reported pose (the refinement's, else the particles' mode) with the
        particles' covariance (the retrieval prior's spread) and the filter's health."""
        if self.particles is None:
            raise InvalidInputError("the filter is not initialised")
        weights = normalise_log_weights(self.log_weights)
        _, cov = weighted_estimate(self.particles, weights)
        mode = self._mode()
        refined = self.refiner is not None and self.refiner.active
        return FilterEstimate(
            pose_world=self.refiner.pose_world if refined else mode,
            covariance=cov,
            effective_sample_size=effective_sample_size(weights),
            n_hypotheses=n_hypotheses,
            lost=self.lost,
            frames_since_support=self.frames_since_support,
            mode_world=mode,
        )


def _frame_estimate(
    hypotheses: Hypotheses, model: MeasurementModel, config: GuardConfig
) -> tuple[np.ndarray, np.ndarray] | None:
    """The frame's own estimate (3,) and its covariance (3, 3) under ``model``: the joint
    pose, else the hypothesis with the most inliers (the first without inlier counts);
    None when the frame has none, or it is not confident (``GuardConfig``)."""
    n = len(hypotheses)
    if n == 0 or (hypotheses.method is not None and "alternative" in hypotheses.method):
        return None
    if hypotheses.joint is not None and hypotheses.joint.any():
        pick = int(np.flatnonzero(hypotheses.joint)[0])
    elif hypotheses.n_inliers is not None:
        pick = int(np.argmax(hypotheses.n_inliers))
    else:
        pick = 0
    centres, covs = model.hypothesis_gaussians(hypotheses)
    cov = 0.5 * (covs[pick] + covs[pick].T)
    if not np.all(np.isfinite(cov)) or math.sqrt(cov[0, 0] + cov[1, 1]) > config.max_spread_m:
        return None
    return centres[pick], cov


def _agrees(a_world: np.ndarray, b_world: np.ndarray, config: FilterConfig) -> np.ndarray:
    """(A, B) bool: pose a_i within the re-seed tolerances of pose b_j."""
    d = a_world[:, None, :2] - b_world[None, :, :2]
    close = np.einsum("abk,abk->ab", d, d) <= config.reseed_position_tol_m**2
    yaw = np.abs(wrap_angle(a_world[:, None, 2] - b_world[None, :, 2]))
    return close & (yaw <= config.reseed_yaw_tol_rad)

"""The vehicle's loop: a particle filter fed frame by frame by a Localizer.

Per frame i: the retrieval prior is the filter's estimate after the last frame it
processed, dead-reckoned with the measured signals to frame i's time (none while the
filter is uninitialised). When hypotheses stop coming or stop agreeing with the
particles, the prior widens frame by frame and then gives way to a search of the whole
map, so that the right map entries come back into reach and the filter can re-seed on
them (it does so only on hypotheses consistent with the vehicle's motion over several
frames, see ParticleFilter); the localizer answers the frame; the filter steps
(``ParticleFilter.step``: predict from frame i - 1 with its measured speed and yaw rate,
then initialise from or update with frame i's hypotheses) and reports its estimate. A
frame without hypotheses (none found, dropped, failed) is a prediction-only step.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from monoloc.client.api import LocalizeAnswer
from monoloc.client.localizer import Localizer
from monoloc.client.motion import advance
from monoloc.client.particle_filter import FilterConfig, FilterEstimate, ParticleFilter
from monoloc.core.errors import InvalidInputError
from monoloc.core.measurement import Hypotheses, MeasurementModel
from monoloc.core.mounting import PlanarMount
from monoloc.core.prior import RetrievalPrior


@dataclass(frozen=True)
class PriorConfig:
    """How the filter's estimate becomes the retrieval prior."""

    sigma_multiplier: float = 3.0
    margin_m: float = 5.0
    min_radius_m: float = 8.0
    max_radius_m: float = 60.0
    yaw_margin_rad: float = math.radians(25.0)
    # Without support (frames with no hypotheses, or hypotheses far from every particle)
    # for more than ``widen_after_frames`` frames, the radius grows by ``widen_factor``
    # per further frame (8 m -> 137 m in 7 frames); after ``global_after_frames`` frames
    # (1 s at 10 Hz) the whole map is searched until the filter has support again.
    widen_after_frames: int = 2
    widen_factor: float = 1.5
    global_after_frames: int = 10


def prior_from_filter(pf: ParticleFilter, config: PriorConfig) -> RetrievalPrior | None:
    """A disc around the filter's estimate whose radius grows with its uncertainty and
    with the frames it has gone without support, or None for a search of the whole map
    (uninitialised, or too long without support)."""
    if not pf.initialised or pf.frames_since_support > config.global_after_frames:
        return None
    est = pf.estimate()
    radius = config.sigma_multiplier * est.position_std_m + config.margin_m
    radius = float(np.clip(radius, config.min_radius_m, config.max_radius_m))
    radius *= config.widen_factor ** max(0, pf.frames_since_support - config.widen_after_frames)
    yaw_std = math.sqrt(max(est.covariance[2, 2], 0.0))
    return RetrievalPrior(
        x_m=float(est.pose_world[0]),
        y_m=float(est.pose_world[1]),
        radius_m=radius,
        yaw_rad=float(est.pose_world[2]),
        yaw_tolerance_rad=float(
            min(math.pi, config.sigma_multiplier * yaw_std + config.yaw_margin_rad)
        ),
    )


def step_signals(signals: np.ndarray, j: int, interpolate: bool = True) -> tuple[float, float]:
    """Speed and yaw rate over the step from frame j to j + 1 out of the per-frame signals
    (N, 2): the mean of both ends (trapezoid) or, ``interpolate`` False, the value at
    frame j. Measured on sim city 41 (bench/accuracy's development city): the value at
    the start lags as the car brakes into and speeds out of corners, and left a +0.025 m
    along-track mean in sharp turns that the mean of both ends removes."""
    if interpolate and j + 1 < len(signals):
        speed, yaw_rate = 0.5 * (signals[j] + signals[j + 1])
    else:
        speed, yaw_rate = signals[j]
    return float(speed), float(yaw_rate)


def dead_reckon_prior(
    prior: RetrievalPrior,
    timestamps_s: np.ndarray,
    signals: np.ndarray,
    last: int,
    i: int,
    interpolate: bool = True,
    mount: PlanarMount = PlanarMount(),
) -> RetrievalPrior:
    """``prior`` (the camera's, at frame ``last``) moved to frame i's time with the
    measured speed and yaw rate (signals (N, 2)) of frames last .. i
    (:func:`step_signals`) by the motion model, the camera at ``mount`` on the vehicle
    (as the particles move); radius and tolerance unchanged."""
    yaw = prior.yaw_rad if prior.yaw_rad is not None else 0.0
    pose = np.array([[prior.x_m, prior.y_m, yaw]])
    for j in range(last, i):
        dt = float(timestamps_s[j + 1] - timestamps_s[j])
        speed, yaw_rate = step_signals(signals, j, interpolate)
        pose = advance(pose, speed, yaw_rate, dt, mount)
    return RetrievalPrior(
        x_m=float(pose[0, 0]),
        y_m=float(pose[0, 1]),
        radius_m=prior.radius_m,
        yaw_rad=float(pose[0, 2]),
        yaw_tolerance_rad=prior.yaw_tolerance_rad,
    )


class Tracker:
    """One run's filter, stepped once per frame in frame order.

    ``timestamps_s`` (N,) and ``signals`` (N, 2: measured speed m/s, yaw rate rad/s) of
    the run; ``estimates_world`` (N, 3) fills in as frames are stepped (NaN before the
    filter initialises). The step from frame i - 1 to i uses the mean of both frames'
    signals (``interpolate_signals``, see :func:`step_signals`). :meth:`prior` and
    :meth:`step` may be called from two threads (frames sent by one, answers handled by
    another).
    """

    def __init__(
        self,
        filter_config: FilterConfig,
        model: MeasurementModel,
        rng: np.random.Generator,
        timestamps_s: np.ndarray,
        signals: np.ndarray,
        prior_config: PriorConfig = PriorConfig(),
        use_prior: bool = True,
        interpolate_signals: bool = True,
    ) -> None:
        self.filter = ParticleFilter(filter_config, model, rng)
        self.timestamps_s = np.asarray(timestamps_s, dtype=np.float64)
        self.signals = np.asarray(signals, dtype=np.float64)
        self.prior_config = prior_config
        self.use_prior = use_prior
        self.interpolate_signals = interpolate_signals
        self.estimates_world = np.full((len(self.timestamps_s), 3), np.nan)
        self.last = -1  # the last frame stepped
        self._lock = threading.Lock()

    def prior(self, i: int) -> RetrievalPrior | None:
        """The retrieval prior of frame i: the estimate after the last frame stepped,
        moved to frame i's time (the filter itself is not touched)."""
        if not self.use_prior:
            return None
        with self._lock:
            prior = prior_from_filter(self.filter, self.prior_config)
            if prior is None or not 0 <= self.last < i:
                return prior
            return dead_reckon_prior(
                prior,
                self.timestamps_s,
                self.signals,
                self.last,
                i,
                self.interpolate_signals,
                self.filter.config.motion.mount,
            )

    def step(self, i: int, hypotheses: Hypotheses) -> FilterEstimate | None:
        """Frame i's filter step (frames in order: i is the frame after the last one);
        the estimate, None while uninitialised. Frame 0 is never predicted: the filter
        starts uninitialised, and the frame that initialises it is not predicted."""
        with self._lock:
            if i != self.last + 1:
                raise InvalidInputError(f"frame {i} stepped after frame {self.last}")
            dt_s, speed_mps, yaw_rate_radps = 0.0, 0.0, 0.0
            if i > 0:
                dt_s = float(self.timestamps_s[i] - self.timestamps_s[i - 1])
                speed_mps, yaw_rate_radps = step_signals(
                    self.signals, i - 1, self.interpolate_signals
                )
            estimate = self.filter.step(dt_s, speed_mps, yaw_rate_radps, hypotheses)
            if estimate is not None:
                self.estimates_world[i] = estimate.pose_world
            self.last = i
            return estimate

    def follow(self, i: int, image, localizer: Localizer, k: int | None = None) -> LocalizeAnswer:
        """Frame i end to end: prior, localize, step; returns the localizer's answer."""
        answer = localizer.localize(image, self.prior(i), k)
        self.step(i, answer.hypotheses)
        return answer


def track(
    tracker: Tracker,
    localizer: Localizer,
    images: Iterable,
    k: int | None = None,
    on_answer: Callable[[int, LocalizeAnswer], None] | None = None,
) -> np.ndarray:
    """Follow every frame of ``images`` (in the localizer's format) in turn; the
    estimates (N, 3). ``on_answer(i, answer)`` after each frame's step."""
    for i, image in enumerate(images):
        answer = tracker.follow(i, image, localizer, k)
        if on_answer is not None:
            on_answer(i, answer)
    return tracker.estimates_world

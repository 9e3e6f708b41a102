"""Replay a run against the map server: stream frames, run the filter, score the result.

For each frame: predict the particles with the measured speed and yaw rate, send the
frame with the filter's prior (a disc around the predicted pose whose radius grows with
the filter's uncertainty; no prior while uninitialised or lost), then update with the
server's hypotheses. In real-time mode frames are sent at their recorded times and the
server may drop stale ones; a dropped frame is a prediction-only step.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from client.api import FrameStream, LocalizeAnswer, MonolocClient, Prior
from client.measurement import Hypotheses, MeasurementModel
from client.particle_filter import FilterConfig, ParticleFilter
from client.replay import ReplayRun
from client.trajectory import TrajectoryMetrics, trajectory_metrics, write_trajectory_files


@dataclass(frozen=True)
class PriorConfig:
    """How the filter's estimate becomes the retrieval prior."""

    sigma_multiplier: float = 3.0
    margin_m: float = 5.0
    min_radius_m: float = 8.0
    max_radius_m: float = 60.0
    yaw_margin_rad: float = math.radians(25.0)


@dataclass(frozen=True)
class DriveConfig:
    filter: FilterConfig = field(default_factory=FilterConfig)
    prior: PriorConfig = field(default_factory=PriorConfig)
    k: int | None = None
    realtime: bool = False
    use_prior: bool = True
    seed: int = 0


@dataclass
class DriveResult:
    """Per-frame estimates (N, 3) (NaN before initialisation), answers and metrics."""

    run: ReplayRun
    estimates_world: np.ndarray
    n_hypotheses: np.ndarray
    dropped: np.ndarray
    latency_ms: np.ndarray
    server_timings_ms: list[dict[str, float]]
    best_hypothesis_world: np.ndarray
    wall_s: float
    metrics: TrajectoryMetrics | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def frames_per_s(self) -> float:
        return len(self.estimates_world) / self.wall_s if self.wall_s > 0 else math.inf


def prior_from_filter(pf: ParticleFilter, config: PriorConfig) -> Prior | None:
    """The retrieval prior for the next frame, or None for a global search."""
    if not pf.initialised or pf.lost:
        return None
    est = pf.estimate()
    radius = config.sigma_multiplier * est.position_std_m + config.margin_m
    yaw_std = math.sqrt(max(est.covariance[2, 2], 0.0))
    return Prior(
        x_m=float(est.pose_world[0]),
        y_m=float(est.pose_world[1]),
        radius_m=float(np.clip(radius, config.min_radius_m, config.max_radius_m)),
        yaw_rad=float(est.pose_world[2]),
        yaw_tolerance_rad=float(
            min(math.pi, config.sigma_multiplier * yaw_std + config.yaw_margin_rad)
        ),
    )


def _best_pose(answer: dict) -> np.ndarray:
    hyps = answer.get("hypotheses") or []
    if not hyps:
        return np.full(3, np.nan)
    best = max(hyps, key=lambda h: h.get("n_inliers", 0))
    return np.array([best["pose"]["x_m"], best["pose"]["y_m"], best["pose"]["yaw_rad"]])


def drive(
    client: MonolocClient,
    map_id: int,
    run: ReplayRun,
    model: MeasurementModel,
    config: DriveConfig = DriveConfig(),
    progress: Callable[[int, int], None] | None = None,
) -> DriveResult:
    """Replay ``run`` over the WebSocket stream and return the filtered trajectory."""
    n = len(run)
    filter_config = config.filter
    if run.lever_arm_m is not None and config.filter.motion.lever_arm_m == 0.0:
        motion = replace(config.filter.motion, lever_arm_m=run.lever_arm_m)
        filter_config = replace(config.filter, motion=motion)
    pf = ParticleFilter(filter_config, model, np.random.default_rng(config.seed))
    estimates = np.full((n, 3), np.nan)
    n_hyps = np.zeros(n, dtype=np.int64)
    dropped = np.zeros(n, dtype=bool)
    latency = np.full(n, np.nan)
    best = np.full((n, 3), np.nan)
    timings: list[dict[str, float]] = [{} for _ in range(n)]
    lock = threading.Lock()
    sent_at = np.zeros(n)
    start = time.perf_counter()

    def step_filter(i: int, hyps: Hypotheses) -> None:
        if i > 0:
            dt = float(run.timestamps_s[i] - run.timestamps_s[i - 1])
            speed, yaw_rate = run.signals[i - 1]
            pf.predict(dt, float(speed), float(yaw_rate))
        if not pf.initialised:
            if len(hyps):
                pf.initialise_from_hypotheses(hyps)
        else:
            pf.update(hyps)
        if pf.initialised:
            estimates[i] = pf.estimate().pose_world

    def handle(i: int, answer: dict) -> None:
        latency[i] = (time.perf_counter() - sent_at[i]) * 1e3
        if answer.get("dropped"):
            dropped[i] = True
            hyps = Hypotheses.empty()
        else:
            parsed = LocalizeAnswer.from_json(answer)
            hyps = parsed.hypotheses
            timings[i] = parsed.timings_ms
            best[i] = _best_pose(answer)
        n_hyps[i] = len(hyps)
        with lock:
            step_filter(i, hyps)
        if progress:
            progress(i + 1, n)

    def current_prior() -> Prior | None:
        if not config.use_prior:
            return None
        with lock:
            return prior_from_filter(pf, config.prior)

    with client.stream(map_id) as stream:
        if config.realtime:
            _drive_realtime(stream, run, sent_at, current_prior, handle, config.k)
        else:
            for i, path in enumerate(run.image_paths):
                prior = None
                if config.use_prior and pf.initialised and not pf.lost:
                    # Predict to this frame's time for the prior; the filter step
                    # re-predicts from the last update, so use a copy.
                    prior = _predicted_prior(pf, run, i, config.prior)
                sent_at[i] = time.perf_counter()
                stream.send(i, float(run.timestamps_s[i]), path.read_bytes(), prior, config.k)
                answer = stream.receive()
                handle(int(answer.get("seq", i)), answer)
    wall = time.perf_counter() - start
    metrics = None
    if run.truth_world is not None:
        metrics = trajectory_metrics(estimates, run.truth_world)
    return DriveResult(
        run, estimates, n_hyps, dropped, latency, timings, best, wall, metrics, list(run.notes)
    )


def _predicted_prior(pf: ParticleFilter, run: ReplayRun, i: int, config: PriorConfig):
    prior = prior_from_filter(pf, config)
    if prior is None or i == 0:
        return prior
    dt = float(run.timestamps_s[i] - run.timestamps_s[i - 1])
    speed, yaw_rate = run.signals[i - 1]
    yaw = prior.yaw_rad if prior.yaw_rad is not None else 0.0
    return Prior(
        x_m=prior.x_m + float(speed) * math.cos(yaw) * dt,
        y_m=prior.y_m + float(speed) * math.sin(yaw) * dt,
        radius_m=prior.radius_m,
        yaw_rad=yaw + float(yaw_rate) * dt,
        yaw_tolerance_rad=prior.yaw_tolerance_rad,
    )


def _drive_realtime(stream: FrameStream, run, sent_at, current_prior, handle, k) -> None:
    """Send at recorded times from a thread; handle answers in order on this one."""
    n = len(run)
    errors: list[BaseException] = []

    def sender() -> None:
        t0 = time.perf_counter()
        try:
            for i, path in enumerate(run.image_paths):
                due = float(run.timestamps_s[i] - run.timestamps_s[0])
                delay = due - (time.perf_counter() - t0)
                if delay > 0:
                    time.sleep(delay)
                sent_at[i] = time.perf_counter()
                stream.send(i, float(run.timestamps_s[i]), path.read_bytes(), current_prior(), k)
        except BaseException as exc:  # noqa: BLE001 - re-raised on the main thread
            errors.append(exc)

    thread = threading.Thread(target=sender, daemon=True)
    thread.start()
    for _ in range(n):
        answer = stream.receive()
        handle(int(answer["seq"]), answer)
    thread.join()
    if errors:
        raise errors[0]


def write_outputs(result: DriveResult, out_prefix: Path) -> tuple[Path, Path]:
    """Trajectory files of the frames that have an estimate."""
    ok = np.all(np.isfinite(result.estimates_world), axis=1)
    return write_trajectory_files(
        out_prefix, result.run.timestamps_s[ok], result.estimates_world[ok]
    )

"""Replay a run against the map server: stream frames, run the filter, score the result.

For each frame: predict the particles with the measured speed and yaw rate, send the
frame with the filter's prior (a disc around the predicted pose whose radius grows with
the filter's uncertainty; no prior while uninitialised or lost), then update with the
server's hypotheses. In real-time mode frames are sent at their recorded times and the
server may drop stale ones; a dropped frame, like a frame the server answered with an
error, is a prediction-only step. Every frame gets exactly one answer, in order; an
answer out of order is an error (the stream guarantees the order).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from monoloc.client.api import FrameStream, LocalizeAnswer, MonolocClient, ServerError
from monoloc.client.particle_filter import FilterConfig, ParticleFilter
from monoloc.client.replay import ReplayRun
from monoloc.client.trajectory import TrajectoryMetrics, trajectory_metrics, write_trajectory_files
from monoloc.core.errors import InvalidInputError
from monoloc.core.measurement import Hypotheses, MeasurementModel
from monoloc.core.prior import RetrievalPrior


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
    # Frames the server answered with an error: frame index -> "code: message".
    errors: dict[int, str] = field(default_factory=dict)
    # When each frame was sent, in seconds after the drive started (N,).
    sent_at_s: np.ndarray | None = None

    @property
    def frames_per_s(self) -> float:
        return len(self.estimates_world) / self.wall_s if self.wall_s > 0 else math.inf


def prior_from_filter(pf: ParticleFilter, config: PriorConfig) -> RetrievalPrior | None:
    """The retrieval prior for the next frame, or None for a global search."""
    if not pf.initialised or pf.lost:
        return None
    est = pf.estimate()
    radius = config.sigma_multiplier * est.position_std_m + config.margin_m
    yaw_std = math.sqrt(max(est.covariance[2, 2], 0.0))
    return RetrievalPrior(
        x_m=float(est.pose_world[0]),
        y_m=float(est.pose_world[1]),
        radius_m=float(np.clip(radius, config.min_radius_m, config.max_radius_m)),
        yaw_rad=float(est.pose_world[2]),
        yaw_tolerance_rad=float(
            min(math.pi, config.sigma_multiplier * yaw_std + config.yaw_margin_rad)
        ),
    )


def _answer_seq(answer: dict, expected: int) -> int:
    """The frame an answer belongs to; the stream answers in order, so it must be
    ``expected``."""
    seq = answer.get("seq")
    if seq != expected:
        raise ServerError(
            f"the stream answered frame {seq} when frame {expected} was due: {str(answer)[:200]}"
        )
    return expected


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
    if n == 0:
        raise InvalidInputError(f"{run.name}: no frames to replay (check the frame range)")
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
    errors: dict[int, str] = {}
    lock = threading.Lock()
    sent_at = np.full(n, np.nan)
    last_done = [-1]  # the last frame the filter has processed
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
        last_done[0] = i

    def handle(i: int, answer: dict) -> None:
        latency[i] = (time.perf_counter() - start - sent_at[i]) * 1e3
        hyps = Hypotheses.empty()
        if answer.get("dropped"):
            dropped[i] = True
        elif "error" in answer:
            err = answer["error"]
            errors[i] = (
                f"{err.get('code', 'error')}: {err.get('message', '')}"
                if isinstance(err, dict)
                else str(err)
            )
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

    def prior_for(i: int) -> RetrievalPrior | None:
        """The prior of frame i: the filter's estimate moved to frame i's time."""
        if not config.use_prior:
            return None
        with lock:
            return _predicted_prior(pf, run, i, config.prior, last_done[0])

    with client.stream(map_id) as stream:
        if config.realtime:
            _drive_realtime(stream, run, sent_at, start, prior_for, handle, config.k)
        else:
            for i, path in enumerate(run.image_paths):
                image = path.read_bytes()
                prior = prior_for(i)
                sent_at[i] = time.perf_counter() - start
                stream.send(i, float(run.timestamps_s[i]), image, prior, config.k)
                answer = stream.receive()
                handle(_answer_seq(answer, i), answer)
    wall = time.perf_counter() - start
    metrics = None
    if run.truth_world is not None:
        metrics = trajectory_metrics(estimates, run.truth_world)
    notes = list(run.notes)
    if errors:
        first = min(errors)
        notes.append(
            f"the server answered {len(errors)} frame(s) with an error (prediction only), "
            f"first frame {first}: {errors[first]}"
        )
    return DriveResult(
        run,
        estimates,
        n_hyps,
        dropped,
        latency,
        timings,
        best,
        wall,
        metrics,
        notes,
        errors,
        sent_at,
    )


def _predicted_prior(
    pf: ParticleFilter, run: ReplayRun, i: int, config: PriorConfig, last: int | None = None
) -> RetrievalPrior | None:
    """The filter's prior after frame ``last`` (default i - 1), dead-reckoned with the
    measured signals to frame i's time (the filter itself is not touched)."""
    prior = prior_from_filter(pf, config)
    last = i - 1 if last is None else last
    if prior is None or last < 0 or last >= i:
        return prior
    x, y = prior.x_m, prior.y_m
    yaw = prior.yaw_rad if prior.yaw_rad is not None else 0.0
    for j in range(last, i):
        dt = float(run.timestamps_s[j + 1] - run.timestamps_s[j])
        speed, yaw_rate = (float(v) for v in run.signals[j])
        x += speed * math.cos(yaw) * dt
        y += speed * math.sin(yaw) * dt
        yaw += yaw_rate * dt
    return RetrievalPrior(
        x_m=x,
        y_m=y,
        radius_m=prior.radius_m,
        yaw_rad=math.atan2(math.sin(yaw), math.cos(yaw)),
        yaw_tolerance_rad=prior.yaw_tolerance_rad,
    )


def _drive_realtime(
    stream: FrameStream,
    run: ReplayRun,
    sent_at: np.ndarray,
    start: float,
    prior_for: Callable[[int], RetrievalPrior | None],
    handle: Callable[[int, dict], None],
    k: int | None,
) -> None:
    """Send at recorded times from a thread; handle answers in order on this one."""
    n = len(run)
    errors: list[BaseException] = []

    def sender() -> None:
        t0 = time.perf_counter()
        try:
            for i, path in enumerate(run.image_paths):
                image = path.read_bytes()
                due = float(run.timestamps_s[i] - run.timestamps_s[0])
                delay = due - (time.perf_counter() - t0)
                if delay > 0:
                    time.sleep(delay)
                prior = prior_for(i)
                sent_at[i] = time.perf_counter() - start
                stream.send(i, float(run.timestamps_s[i]), image, prior, k)
        except BaseException as exc:  # noqa: BLE001 - re-raised on the main thread
            errors.append(exc)

    thread = threading.Thread(target=sender, daemon=True)
    thread.start()
    try:
        for i in range(n):
            if errors:
                break
            answer = stream.receive()
            handle(_answer_seq(answer, i), answer)
    finally:
        thread.join(timeout=5.0)
    if errors:
        raise errors[0]


def write_outputs(result: DriveResult, out_prefix: Path) -> tuple[Path, Path]:
    """Trajectory files of the frames that have an estimate."""
    ok = np.all(np.isfinite(result.estimates_world), axis=1)
    return write_trajectory_files(
        out_prefix, result.run.timestamps_s[ok], result.estimates_world[ok]
    )

"""The closed loop: a vehicle steered on monoloc's own estimate.

Simulated time advances in the vehicle's integration steps (``world.dt_s``); the
controller acts at every step on a believed rear-axle pose. At each camera frame the
world is rendered at the vehicle's true pose (with depth when the lap is recorded for
mapping); with a localizer the frame goes to the map server through the client, and the
client's particle filter (``monoloc.client.tracking.Tracker``) fuses the answer with the
measured speed and yaw rate. The estimate of frame i (a pose at frame time t_i) reaches
the controller at t_i + latency_i, latency_i being the measured round trip of that
request (or a draw from a recorded distribution); meanwhile, and after, the controller
dead-reckons from the last estimate it received with the measured signals, as on a car.
While a request is out, the frames that fall due are not sent (prediction-only steps).

Modes: ``open`` (the controller acts on the ground truth; localization, if any, only
watches) and ``closed`` (the controller acts on the estimate; before the first estimate
arrives, on the known start pose dead-reckoned with the measured signals).

Controllers: ``pid`` (``sim.control.TrackingController``) or ``mpc``
(``sim.mpc.MpcController``), which is handed the localization's quality (the filter's
position and yaw std, the known-feature share of the last answered frame) each time an
estimate reaches it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from monoloc.client.api import LocalizeAnswer
from monoloc.client.localizer import Localizer
from monoloc.client.particle_filter import FilterConfig
from monoloc.client.tracking import Tracker
from monoloc.core.errors import InvalidInputError
from monoloc.core.measurement import Hypotheses, MeasurementModel
from monoloc.sim.closed_loop_world import (
    Lap,
    SignalErrors,
    planar_from_vehicle,
    vehicle_from_planar,
)
from monoloc.sim.control import (
    BicycleState,
    TrackingController,
    step_bicycle,
    tracking_error,
)
from monoloc.sim.mpc import LocalizationQuality, MpcConfig, MpcController, quality_factor

MODES = ("open", "closed")
CONTROLLERS = ("pid", "mpc")


@dataclass(frozen=True)
class LoopConfig:
    """One drive: ``mode`` open|closed, ``laps`` of the reference path, at most
    ``max_frames`` camera frames (None: the whole path); ``disturbance``: add the
    world's sinusoidal steering disturbance (oscillating, off-center laps);
    ``recorded_latency_ms``: draw each answer's delay from these values instead of
    using the measured round trip; ``k``: entries the server retrieves (None: its
    default); ``seed``: render noise, signal errors and the filter; ``controller``:
    pid|mpc (the disturbance is the PID's: the MPC drives undisturbed laps only)."""

    mode: str = "closed"
    laps: float = 1.0
    max_frames: int | None = None
    disturbance: bool = False
    lap: Lap = field(default_factory=Lap)
    recorded_latency_ms: tuple[float, ...] | None = None
    k: int | None = None
    seed: int = 0
    first_frame_s: float = 0.1
    controller: str = "pid"

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise InvalidInputError(f"mode must be one of {MODES}, got {self.mode!r}")
        if self.controller not in CONTROLLERS:
            raise InvalidInputError(
                f"controller must be one of {CONTROLLERS}, got {self.controller!r}"
            )
        if self.controller == "mpc" and self.disturbance:
            raise InvalidInputError(
                "the steering disturbance (oscillating laps) is the PID's; use controller='pid'"
            )
        if self.laps <= 0:
            raise InvalidInputError("laps must be positive")
        if self.max_frames is not None and self.max_frames < 1:
            raise InvalidInputError("max_frames must be at least 1")
        if self.recorded_latency_ms is not None and (
            not self.recorded_latency_ms or min(self.recorded_latency_ms) < 0
        ):
            raise InvalidInputError("recorded latencies must be a non-empty list of values >= 0")


@dataclass
class FrameLog:
    """Per camera frame (all (N,) unless said): time, true vehicle state and camera
    pose, the estimate (camera planar pose, NaN before initialisation), the pose the
    controller believed at that time (rear axle), the command, the true tracking errors,
    the measured signals, the server's answer in numbers, the round trip, the filter's
    position and yaw std (m, rad; NaN before initialisation), and the localization
    quality q the MPC held (``sim.mpc.quality_factor``; NaN with the PID)."""

    t_s: list = field(default_factory=list)
    truth_vehicle: list = field(default_factory=list)  # (x, y, yaw)
    truth_cam: list = field(default_factory=list)  # planar (X, Y, psi)
    T_world_from_cam: list = field(default_factory=list)  # (4, 4)
    believed_vehicle: list = field(default_factory=list)
    command: list = field(default_factory=list)  # (steer rad, accel m/s^2)
    lateral_m: list = field(default_factory=list)
    heading_rad: list = field(default_factory=list)
    signals: list = field(default_factory=list)  # measured (speed, yaw rate)
    sent: list = field(default_factory=list)
    n_hypotheses: list = field(default_factory=list)
    n_features: list = field(default_factory=list)
    n_matched: list = field(default_factory=list)
    n_inliers: list = field(default_factory=list)
    latency_ms: list = field(default_factory=list)
    filter_std: list = field(default_factory=list)  # (position m, yaw rad)
    mpc_quality: list = field(default_factory=list)


@dataclass
class LoopResult:
    """A finished drive: per-frame arrays (see FrameLog; a world with a tracker adds
    ``recorded_cam`` (N, 3), the truth as it records it), the estimates (N, 3), the
    integration-rate true trace (t, x, y, yaw, lateral error) and what it took."""

    config: LoopConfig
    frames: dict[str, np.ndarray]
    estimates_world: np.ndarray
    trace: dict[str, np.ndarray]
    lane_half_width_m: float
    wall_s: float
    notes: list[str] = field(default_factory=list)

    @property
    def n_frames(self) -> int:
        return len(self.frames["t_s"])

    @property
    def known_share(self) -> np.ndarray:
        """Share of the query's features that the map knows: inlier map points of the
        best answer over the query's features (0 without an answer)."""
        f = self.frames["n_features"].astype(np.float64)
        return np.where(f > 0, self.frames["n_inliers"] / np.maximum(f, 1.0), 0.0)


def answer_counts(answer: LocalizeAnswer) -> tuple[int, int, int]:
    """(query features, matched map points, inlier map points) of an answer: the counts of
    its best per-entry hypothesis (most inliers; a joint hypothesis is left out: it counts
    the union over several entries, which may exceed the query's features), 0 without
    one."""
    raw = answer.raw or {}
    n_features = int(raw.get("n_features") or 0)
    hyps = [h for h in raw.get("hypotheses") or [] if not h.get("joint", False)]
    if not hyps:
        return n_features, 0, 0
    best = max(hyps, key=lambda h: h.get("n_inliers", 0))
    return n_features, int(best.get("n_matches", 0)), int(best.get("n_inliers", 0))


class _Odometry:
    """The vehicle's own dead reckoning with its measured signals (rear axle), kept at
    every step so that an estimate of an earlier time can be moved to now."""

    def __init__(self, start: BicycleState, dt_s: float) -> None:
        self.dt_s = dt_s
        self.pose = [(start.x_m, start.y_m, start.yaw_rad)]

    def advance(self, speed: float, yaw_rate: float) -> None:
        x, y, yaw = self.pose[-1]
        dt = self.dt_s
        mid = yaw + 0.5 * yaw_rate * dt
        self.pose.append(
            (x + speed * dt * math.cos(mid), y + speed * dt * math.sin(mid), yaw + yaw_rate * dt)
        )

    def at(self, t_s: float) -> tuple[float, float, float]:
        """The pose at the step nearest ``t_s`` (steps are ``dt_s`` apart from 0)."""
        return self.pose[int(np.clip(round(t_s / self.dt_s), 0, len(self.pose) - 1))]


def _relative(a, b) -> tuple[float, float, float]:
    """b expressed in a's frame (SE2)."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    c, s = math.cos(a[2]), math.sin(a[2])
    return c * dx + s * dy, -s * dx + c * dy, b[2] - a[2]


def _compose(a, rel) -> tuple[float, float, float]:
    c, s = math.cos(a[2]), math.sin(a[2])
    return a[0] + c * rel[0] - s * rel[1], a[1] + s * rel[0] + c * rel[1], a[2] + rel[2]


def _measured(state: BicycleState, world, run_errors, noise) -> tuple[float, float]:
    """Speed and yaw rate as the car's encoder and gyro report them."""
    speed_scale, speed_bias, yaw_bias = run_errors
    e: SignalErrors = world.signal_errors
    speed = state.speed_mps * speed_scale + speed_bias + e.speed_noise_mps * noise[0]
    yaw_rate = state.yaw_rate_radps(world.bicycle) + yaw_bias + e.yaw_rate_noise_radps * noise[1]
    return max(speed, 0.0), yaw_rate


def T_world_from_vehicle_flat(x_m: float, y_m: float, yaw_rad: float) -> np.ndarray:
    T = np.eye(4)
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    T[:2, :2] = [[c, -s], [s, c]]
    T[0, 3], T[1, 3] = x_m, y_m
    return T


FrameSink = Callable[[int, float, np.ndarray, "np.ndarray | None", np.ndarray], None]


def run_loop(
    world,
    config: LoopConfig,
    localizer: Localizer | None = None,
    model: MeasurementModel | None = None,
    filter_config: FilterConfig | None = None,
    sink: FrameSink | None = None,
    with_depth: bool = False,
    encode: Callable[[np.ndarray], bytes] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> LoopResult:
    """Drive ``config.laps`` of ``world``'s reference path (see the module docstring).
    ``localizer`` (+ ``model``, ``filter_config``): localize every frame through it;
    none: just drive (a mapping lap, open loop). ``sink(i, t_s, image, depth_m,
    T_world_from_cam)``: called with every rendered frame (the recorder)."""
    if config.mode == "closed" and localizer is None:
        raise InvalidInputError("a closed-loop drive needs a localizer")
    if localizer is not None and model is None:
        raise InvalidInputError("localizing needs the map's measurement model")
    encode = encode or encode_png
    rng = np.random.default_rng([config.seed, 16])
    path = world.reference_path(config.laps, config.lap.room)
    controller = make_controller(
        config.controller, world, path, config.disturbance, float(rng.uniform(0, 2 * math.pi))
    )
    lighting = world.lighting(config.lap)
    e: SignalErrors = world.signal_errors
    run_errors = (
        1.0 + e.speed_scale_error * rng.standard_normal(),
        e.speed_bias_mps * rng.standard_normal(),
        e.yaw_rate_bias_radps * rng.standard_normal(),
    )
    dt, period = world.dt_s, 1.0 / world.frame_rate_hz
    # Frames are known in advance only by their count: allocate for the whole path.
    n_alloc = int(path.length_m / world.reference_speed_mps / period * 1.5) + 16
    if config.max_frames is not None:
        n_alloc = min(n_alloc, config.max_frames)
    tracker = None
    if localizer is not None:
        tracker = Tracker(
            filter_config or FilterConfig(),
            model,
            np.random.default_rng([config.seed, 17]),
            np.zeros(n_alloc),
            np.zeros((n_alloc, 2)),
        )
    state = world.start_state(path)
    odom = _Odometry(state, dt)
    belief_anchor = (0.0, (state.x_m, state.y_m, state.yaw_rad))  # (t, pose at t)
    pending: list[tuple[float, int, np.ndarray, LocalizationQuality]] = []
    known_share = 0.0  # of the last frame that was sent
    busy_until = -math.inf
    log = FrameLog()
    trace: list[tuple[float, float, float, float, float]] = []
    t, next_frame = 0.0, config.first_frame_s
    i = 0
    started = time.perf_counter()
    signal = _measured(state, world, run_errors, rng.standard_normal(2))
    truth_hint = 0
    while True:
        true_err = tracking_error(path, state.x_m, state.y_m, state.yaw_rad, truth_hint)
        truth_hint = true_err.index
        if controller.at_end or truth_hint >= len(path.s_m) - 2 or i >= n_alloc:
            break
        if t >= next_frame - 1e-9:
            T_wc = T_world_from_vehicle_flat(state.x_m, state.y_m, state.yaw_rad) @ (
                world.T_vehicle_from_cam
            )
            frame_rng = np.random.default_rng([config.seed, 3, i])
            image, depth = world.render(config.lap, lighting, T_wc, frame_rng, with_depth)
            log.t_s.append(t)
            log.truth_vehicle.append((state.x_m, state.y_m, state.yaw_rad))
            log.truth_cam.append(
                planar_from_vehicle(state.x_m, state.y_m, state.yaw_rad, world.lever_arm_m)
            )
            log.T_world_from_cam.append(T_wc)
            log.signals.append(signal)
            log.lateral_m.append(true_err.lateral_m)
            log.mpc_quality.append(
                quality_factor(controller.quality, controller.config)
                if isinstance(controller, MpcController)
                else math.nan
            )
            log.heading_rad.append(true_err.heading_rad)
            if tracker is not None:
                tracker.timestamps_s[i] = t
                tracker.signals[i] = signal
                latency_s, answer, sent = _localize(
                    tracker, localizer, image, i, t, busy_until, config, encode, rng
                )
                if sent:
                    busy_until = t + latency_s
                estimate = tracker.step(i, answer.hypotheses)
                counts = answer_counts(answer)
                if sent:
                    known_share = counts[2] / counts[0] if counts[0] > 0 else 0.0
                if estimate is not None:
                    quality = quality_of(estimate, known_share)
                    pending.append((t + latency_s, i, estimate.pose_world.copy(), quality))
                    log.filter_std.append((quality.position_std_m, quality.yaw_std_rad))
                else:
                    log.filter_std.append((math.nan, math.nan))
                log.sent.append(sent)
                log.n_hypotheses.append(len(answer.hypotheses))
                log.latency_ms.append(1e3 * latency_s if sent else math.nan)
            else:
                counts = (0, 0, 0)
                log.filter_std.append((math.nan, math.nan))
                log.sent.append(False)
                log.n_hypotheses.append(0)
                log.latency_ms.append(math.nan)
            log.n_features.append(counts[0])
            log.n_matched.append(counts[1])
            log.n_inliers.append(counts[2])
            if sink is not None:
                sink(i, t, image, depth, T_wc)
            i += 1
            next_frame += period
            if progress is not None:
                progress(i, n_alloc)
        # Estimates whose answer has arrived become the controller's new anchor.
        while pending and pending[0][0] <= t + 1e-12:
            _, k, pose_cam, quality = pending.pop(0)
            belief_anchor = (log.t_s[k], vehicle_from_planar(pose_cam, world.lever_arm_m))
            if isinstance(controller, MpcController):
                controller.set_quality(quality)
        if config.mode == "open":
            believed = (state.x_m, state.y_m, state.yaw_rad)
        else:
            t_anchor, anchor = belief_anchor
            believed = _compose(anchor, _relative(odom.at(t_anchor), odom.pose[-1]))
        command, _ = controller.command(t, *believed, signal[0], dt)
        if len(log.believed_vehicle) < len(log.t_s):
            log.believed_vehicle.append(believed)
            log.command.append((command.steer_rad, command.accel_mps2))
        trace.append((t, state.x_m, state.y_m, state.yaw_rad, true_err.lateral_m))
        state = step_bicycle(state, command, world.bicycle, dt)
        t += dt
        signal = _measured(state, world, run_errors, rng.standard_normal(2))
        odom.advance(signal[0], signal[1])
    n = len(log.t_s)
    if n == 0:
        raise InvalidInputError("the drive ended before its first frame")
    frames = {name: np.asarray(values) for name, values in vars(log).items()}
    frames["believed_vehicle"] = frames["believed_vehicle"][:n]
    recorded = getattr(world, "tracker_poses", None)
    if recorded is not None:  # the truth as the room's tracker records it (the judge's)
        T_rec = recorded(frames["T_world_from_cam"], np.random.default_rng([config.seed, 42]),
                         frames["t_s"])  # fmt: skip
        frames["recorded_cam"] = planar_of_cam(T_rec)
    estimates = (
        tracker.estimates_world[:n].copy() if tracker is not None else np.full((n, 3), np.nan)
    )
    tr = np.asarray(trace)
    return LoopResult(
        config=config,
        frames=frames,
        estimates_world=estimates,
        trace={
            "t_s": tr[:, 0],
            "x_m": tr[:, 1],
            "y_m": tr[:, 2],
            "yaw_rad": tr[:, 3],
            "lateral_m": tr[:, 4],
        },
        lane_half_width_m=world.lane_half_width_m,
        wall_s=time.perf_counter() - started,
    )


def planar_of_cam(T_world_from_cam: np.ndarray) -> np.ndarray:
    """(n, 3) planar poses (X, Y, psi) of camera poses (n, 4, 4) in a z-up world: the
    position and the heading of the optical axis."""
    T = np.asarray(T_world_from_cam, dtype=np.float64)
    return np.column_stack([T[:, 0, 3], T[:, 1, 3], np.arctan2(T[:, 1, 2], T[:, 0, 2])])


def make_controller(
    name: str, world, path, disturbance: bool = False, phase_rad: float = 0.0
) -> TrackingController | MpcController:
    """The world's ``pid`` (its ControllerConfig, with or without the disturbance) or
    ``mpc`` (MpcConfig.for_vehicle at the world's reference speed; the mapped corridor's
    half width is 40 % of the lane's: the centre-line laps' views, not the whole lane)."""
    if name == "pid":
        return TrackingController(
            path, world.controller_config(disturbance, phase_rad), world.bicycle
        )
    if name == "mpc":
        if disturbance:
            raise InvalidInputError("the MPC drives no disturbed laps; use the pid controller")
        config = MpcConfig.for_vehicle(
            world.bicycle, world.reference_speed_mps, 0.4 * world.lane_half_width_m
        )
        return MpcController(path, config, world.bicycle)
    raise InvalidInputError(f"controller must be one of {CONTROLLERS}, got {name!r}")


def quality_of(estimate, known_share: float) -> LocalizationQuality:
    """The MPC's view of a filter estimate (``FilterEstimate``) and a known-feature share."""
    cov = np.asarray(estimate.covariance, dtype=np.float64)
    return LocalizationQuality(
        position_std_m=float(estimate.position_std_m),
        yaw_std_rad=float(math.sqrt(max(cov[2, 2], 0.0))),
        known_share=float(min(max(known_share, 0.0), 1.0)),
    )


def concat_passes(results: list[LoopResult]) -> LoopResult:
    """Several drives over the same stretch (a route that is no loop, driven again from its
    start) as one result: frames, estimates and trace one after the other, each pass's
    times shifted to follow the previous pass (one frame period apart), and
    ``frames["pass_index"]`` saying which pass a frame belongs to (the metrics let each
    pass's filter settle). One result is returned as it is, with its pass index."""
    if not results:
        raise InvalidInputError("no drive to concatenate")
    frames: dict[str, list[np.ndarray]] = {name: [] for name in results[0].frames}
    frames["pass_index"] = []
    trace: dict[str, list[np.ndarray]] = {name: [] for name in results[0].trace}
    offset_s = 0.0
    for index, result in enumerate(results):
        for name, values in result.frames.items():
            frames[name].append(values + offset_s if name == "t_s" else values)
        frames["pass_index"].append(np.full(result.n_frames, index, dtype=np.int64))
        for name, values in result.trace.items():
            trace[name].append(values + offset_s if name == "t_s" else values)
        t = result.frames["t_s"]
        period_s = float(np.median(np.diff(t))) if len(t) > 1 else 0.1
        offset_s += float(max(t[-1], result.trace["t_s"][-1])) + period_s
    first = results[0]
    return LoopResult(
        config=first.config,
        frames={name: np.concatenate(parts) for name, parts in frames.items()},
        estimates_world=np.concatenate([r.estimates_world for r in results]),
        trace={name: np.concatenate(parts) for name, parts in trace.items()},
        lane_half_width_m=first.lane_half_width_m,
        wall_s=float(sum(r.wall_s for r in results)),
        notes=[note for r in results for note in r.notes],
    )


def _localize(tracker, localizer, image, i, t, busy_until, config, encode, rng):
    """(delay s, answer, sent) of frame i: not sent while the previous request is out."""
    if t < busy_until:
        return 0.0, LocalizeAnswer(Hypotheses.empty(), None, {}, {"dropped": True}, True), False
    payload = encode(image)
    start = time.perf_counter()
    answer = localizer.localize(payload, tracker.prior(i), config.k)
    latency_s = time.perf_counter() - start
    if config.recorded_latency_ms is not None:
        latency_s = 1e-3 * float(rng.choice(np.asarray(config.recorded_latency_ms)))
    return latency_s, answer, True


def encode_png(image: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise InvalidInputError("could not encode a frame as PNG")
    return buf.tobytes()

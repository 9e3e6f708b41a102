"""Replay a run against the map server over the WebSocket stream, through the vehicle's
loop (monoloc.client.tracking), and score the result.

Every frame goes out with the filter's prior (moved to the frame's time) and is answered
once, in order; an answer out of order is an error (the stream guarantees the order).
In real-time mode frames are sent at their recorded times from a thread and the server
may drop stale ones; a dropped frame, like a frame the server answered with an error, is
a prediction-only step.

The run's camera is registered with the server once (``MonolocClient.camera_id``: an
equal camera registered before is reused) and every frame names it by its id. The
map's geographic reference is read once, before the first frame; with one, the
drive's track can also be written as GeoJSON (monoloc.client.geojson).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from monoloc.client.api import FrameStream, LocalizeAnswer, MonolocClient
from monoloc.client.geojson import track_geojson, write_track_geojson
from monoloc.client.localizer import Localizer, StreamLocalizer, check_answer_seq
from monoloc.client.particle_filter import FilterConfig
from monoloc.client.replay import ReplayRun
from monoloc.client.tracking import PriorConfig, Tracker, track
from monoloc.client.trajectory import TrajectoryMetrics, trajectory_metrics, write_trajectory_files
from monoloc.core.errors import InvalidInputError
from monoloc.core.geo import GeoReference
from monoloc.core.measurement import MeasurementModel
from monoloc.core.mounting import PlanarMount
from monoloc.core.prior import RetrievalPrior


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
    # Per frame: the OGC GeoPose of the best hypothesis (geo-referenced maps), or None.
    geoposes: list[dict | None] = field(default_factory=list)
    # Per frame (N,): world z (m) of the best hypothesis' camera, NaN without one.
    best_height_m: np.ndarray | None = None
    # The map's geographic reference when it has one (read once per drive).
    geo_reference: GeoReference | None = None
    # Where the camera sat on the vehicle in the motion model (the reported vehicle pose).
    mount: PlanarMount = field(default_factory=PlanarMount)

    @property
    def vehicle_world(self) -> np.ndarray:
        """The vehicle's planar poses (N, 3) (its reference point, heading of its x axis):
        the filter's camera estimates moved through the mounting (NaN where they are)."""
        return self.mount.vehicle_from_camera(self.estimates_world)

    @property
    def all_refused(self) -> bool:
        """Whether the server answered every frame with an error."""
        return bool(len(self.estimates_world)) and len(self.errors) == len(self.estimates_world)

    @property
    def frames_per_s(self) -> float:
        return len(self.estimates_world) / self.wall_s if self.wall_s > 0 else math.inf


class _DriveLog:
    """What a drive records per frame besides the estimates (all (N,) or lists of N)."""

    def __init__(self, n: int) -> None:
        self.start = time.perf_counter()
        self.n_hypotheses = np.zeros(n, dtype=np.int64)
        self.dropped = np.zeros(n, dtype=bool)
        self.latency_ms = np.full(n, np.nan)
        self.sent_at_s = np.full(n, np.nan)
        self.best_world = np.full((n, 3), np.nan)
        self.best_height_m = np.full(n, np.nan)
        self.timings_ms: list[dict[str, float]] = [{} for _ in range(n)]
        self.errors: dict[int, str] = {}
        self.geoposes: list[dict | None] = [None] * n

    def sent(self, i: int) -> None:
        self.sent_at_s[i] = time.perf_counter() - self.start

    def answered(self, i: int) -> None:
        self.latency_ms[i] = (time.perf_counter() - self.start - self.sent_at_s[i]) * 1e3

    def record(self, i: int, answer: LocalizeAnswer) -> None:
        self.dropped[i] = answer.dropped
        if answer.error is not None:
            self.errors[i] = answer.error
        self.n_hypotheses[i] = len(answer.hypotheses)
        self.timings_ms[i] = answer.timings_ms
        self.best_world[i] = answer.best_pose_world
        self.best_height_m[i] = answer.best_height_m
        self.geoposes[i] = answer.best_geopose

    def result(
        self, run: ReplayRun, estimates_world: np.ndarray, geo: GeoReference | None
    ) -> DriveResult:
        wall = time.perf_counter() - self.start
        metrics = None
        if run.truth_world is not None:
            metrics = trajectory_metrics(estimates_world, run.truth_world)
        notes = list(run.notes)
        if self.errors:
            first = min(self.errors)
            notes.append(
                f"the server answered {len(self.errors)} frame(s) with an error (prediction "
                f"only), first frame {first}: {self.errors[first]}"
            )
        return DriveResult(
            run,
            estimates_world,
            self.n_hypotheses,
            self.dropped,
            self.latency_ms,
            self.timings_ms,
            self.best_world,
            wall,
            metrics,
            notes,
            self.errors,
            self.sent_at_s,
            self.geoposes,
            self.best_height_m,
            geo,
        )


def run_filter_config(config: FilterConfig, run: ReplayRun) -> FilterConfig:
    """``config`` with the run's camera mounting (or only its lever arm, when that is all
    the recording says) unless the config sets a mounting or a lever arm itself."""
    motion = config.motion
    if motion.mounting is not None or motion.lever_arm_m != 0.0:
        return config
    if run.mounting is not None:
        return replace(config, motion=replace(motion, mounting=run.mounting))
    if run.lever_arm_m is not None:
        return replace(config, motion=replace(motion, lever_arm_m=run.lever_arm_m))
    return config


def drive(
    client: MonolocClient,
    map_id: int,
    run: ReplayRun,
    model: MeasurementModel,
    config: DriveConfig = DriveConfig(),
    progress: Callable[[int, int], None] | None = None,
) -> DriveResult:
    """Replay ``run`` over the WebSocket stream and return the filtered trajectory (with
    the map's geographic reference, read first, when it has one)."""
    if len(run) == 0:
        raise InvalidInputError(f"{run.name}: no frames to replay (check the frame range)")
    if run.intrinsics is None:
        raise InvalidInputError(
            f"{run.name}: the camera that took the frames is unknown (KITTI calib.txt, a TUM "
            "run's camera.json or a bag's CameraInfo; or --camera): the vehicle does not "
            "assume the map's camera"
        )
    # the run's camera is registered once (or found registered) and named by its id
    camera_id = client.camera_id(run.intrinsics)
    geo = client.geo_reference(map_id)
    with client.stream(map_id) as stream:
        if not config.realtime:
            localizer = StreamLocalizer(stream, run.timestamps_s, camera_id=camera_id)
            return drive_with(localizer, run, model, config, geo, progress)
        filter_config = run_filter_config(config.filter, run)
        tracker = _tracker(filter_config, model, run, config)
        log = _DriveLog(len(run))
        _drive_realtime(stream, run, tracker, log, config.k, _recorder(log, progress), camera_id)
    return replace(log.result(run, tracker.estimates_world, geo), mount=filter_config.motion.mount)


def _recorder(log: _DriveLog, progress: Callable[[int, int], None] | None):
    """The per-frame callback: the answer logged, then the progress told."""

    def recorded(i: int, answer: LocalizeAnswer) -> None:
        log.record(i, answer)
        if progress:
            progress(i + 1, len(log.n_hypotheses))

    return recorded


def drive_with(
    localizer: Localizer,
    run: ReplayRun,
    model: MeasurementModel,
    config: DriveConfig = DriveConfig(),
    geo: GeoReference | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> DriveResult:
    """Replay ``run`` through any Localizer taking encoded frames (e.g. the sharded one,
    monoloc.client.sharded), one frame at a time in order; ``geo``: the map's reference."""
    if len(run) == 0:
        raise InvalidInputError(f"{run.name}: no frames to replay (check the frame range)")
    filter_config = run_filter_config(config.filter, run)
    tracker = _tracker(filter_config, model, run, config)
    log = _DriveLog(len(run))
    images = (run.image_bytes(i) for i in range(len(run)))
    track(tracker, _Timed(localizer, log), images, config.k, _recorder(log, progress))
    return replace(log.result(run, tracker.estimates_world, geo), mount=filter_config.motion.mount)


def _tracker(
    filter_config: FilterConfig, model: MeasurementModel, run: ReplayRun, config: DriveConfig
) -> Tracker:
    return Tracker(
        filter_config,
        model,
        np.random.default_rng(config.seed),
        run.timestamps_s,
        run.signals,
        config.prior,
        config.use_prior,
    )


class _Timed:
    """A localizer whose calls are logged as sent and answered frames (0, 1, ...)."""

    def __init__(self, localizer: Localizer, log: _DriveLog) -> None:
        self.localizer, self.log = localizer, log
        self.seq = 0

    def localize(
        self, image: bytes, prior: RetrievalPrior | None = None, k: int | None = None
    ) -> LocalizeAnswer:
        i = self.seq
        self.seq += 1
        self.log.sent(i)
        answer = self.localizer.localize(image, prior, k)
        self.log.answered(i)
        return answer


def _drive_realtime(
    stream: FrameStream,
    run: ReplayRun,
    tracker: Tracker,
    log: _DriveLog,
    k: int | None,
    recorded: Callable[[int, LocalizeAnswer], None],
    camera_id: int,
) -> None:
    """Send at recorded times from a thread (each frame naming the registered camera
    ``camera_id``); step the tracker with the answers in order on this one."""
    errors: list[BaseException] = []

    def sender() -> None:
        t0 = time.perf_counter()
        try:
            for i in range(len(run)):
                image = run.image_bytes(i)
                due = float(run.timestamps_s[i] - run.timestamps_s[0])
                delay = due - (time.perf_counter() - t0)
                if delay > 0:
                    time.sleep(delay)
                prior = tracker.prior(i)
                log.sent(i)
                stream.send(i, float(run.timestamps_s[i]), image, prior, k, camera_id=camera_id)
        except BaseException as exc:  # noqa: BLE001 - re-raised on the main thread
            errors.append(exc)

    thread = threading.Thread(target=sender, daemon=True)
    thread.start()
    try:
        for i in range(len(run)):
            if errors:
                break
            data = stream.receive()
            check_answer_seq(data, i)
            log.answered(i)
            answer = LocalizeAnswer.from_stream(data)
            tracker.step(i, answer.hypotheses)
            recorded(i, answer)
    finally:
        thread.join(timeout=5.0)
    if errors:
        raise errors[0]


def write_geojson(result: DriveResult, out_prefix: Path) -> Path | None:
    """``<prefix>.geojson`` of the filter's track (monoloc.client.geojson) when the map is
    geo-referenced and the filter gave an estimate; None otherwise."""
    if result.geo_reference is None:
        return None
    n = len(result.estimates_world)
    collection = track_geojson(
        result.run.name,
        result.geo_reference,
        result.run.timestamps_s,
        result.estimates_world,
        result.n_hypotheses,
        result.best_height_m if result.best_height_m is not None else np.full(n, np.nan),
        result.geoposes or [None] * n,
    )
    if collection is None:
        return None
    return write_track_geojson(out_prefix.with_name(out_prefix.name + ".geojson"), collection)


def write_bag(result: DriveResult, path: Path, storage: str = "sqlite3") -> Path | None:
    """A new ROS 2 bag folder ``path`` with the filter's track as ``nav_msgs/Odometry`` on
    /monoloc/odometry (monoloc.core.formats.rosbag.write_pose_bag): one message per frame
    with an estimate, stamped with the frame's time, the camera's pose in the map's world
    (``map``) at the GeoJSON track's height (held median of the best hypotheses' heights);
    the child frame is the replayed bag's camera frame. None when the filter gave no
    estimate. Needs ``rosbags`` (the formats extra)."""
    from monoloc.client.geojson import track_heights_m
    from monoloc.core.formats.rosbag import write_pose_bag
    from monoloc.core.geometry import T_world_from_cam_planar

    ok = np.all(np.isfinite(result.estimates_world), axis=1)
    if not ok.any():
        return None
    n = len(result.estimates_world)
    best = result.best_height_m if result.best_height_m is not None else np.full(n, np.nan)
    heights = track_heights_m(best)
    poses = np.stack(
        [
            T_world_from_cam_planar(*result.estimates_world[i], height_m=heights[i])
            for i in np.flatnonzero(ok)
        ]
    )
    return write_pose_bag(
        path,
        result.run.timestamps_s[ok],
        poses,
        camera_frame=result.run.camera_frame or "camera_optical_frame",
        storage=storage,
    )


def write_outputs(result: DriveResult, out_prefix: Path) -> tuple[Path, Path]:
    """Trajectory files of the frames that have an estimate (the camera's poses)."""
    ok = np.all(np.isfinite(result.estimates_world), axis=1)
    return write_trajectory_files(
        out_prefix, result.run.timestamps_s[ok], result.estimates_world[ok]
    )


def write_vehicle_track(result: DriveResult, out_prefix: Path) -> Path | None:
    """``<prefix>.vehicle.tum.txt``: the vehicle's poses (T_world_from_vehicle, x forward,
    z up, on the ground plane) of the frames with an estimate, in TUM's format; None
    without any."""
    from monoloc.core.formats import tum

    vehicle = result.vehicle_world
    ok = np.all(np.isfinite(vehicle), axis=1)
    if not ok.any():
        return None
    poses = np.tile(np.eye(4), (int(ok.sum()), 1, 1))
    c, s = np.cos(vehicle[ok, 2]), np.sin(vehicle[ok, 2])
    poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = c, -s, s, c
    poses[:, :2, 3] = vehicle[ok, :2]
    path = out_prefix.with_name(out_prefix.name + ".vehicle.tum.txt")
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as fh:
        tum.write_trajectory(fh, result.run.timestamps_s[ok], poses)
    return path

"""Generate a KITTI-like dataset of one city: plan the runs, render them, write files.

Runs (one KITTI sequence each, numbered in the order given):

- ``map``: the main district's route in the lane centre, by day.
- ``query``: the same route later: smooth lateral offsets up to +-1.5 m (heading
  deviations up to ~5 deg), some parked cars moved, another sun position (or the
  lighting given by ``query_lighting``).
- ``train``: a route through the training district (never seen by the others).
- ``night``: the query route at night (its own offsets and parked cars).
- ``offcenter``: the map route with a sinusoidal steering disturbance, same lighting
  and cars as the map (the paper's map augmentation).

World frame of every ``poses/NN.txt``: the camera-0 frame of the first frame of the
``map`` run as written (or of the first run when there is no map run), in KITTI's
convention; see :func:`kitti_world`. Generation is deterministic in the seed: the same
config gives the same bytes, whatever the number of worker processes.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from client.camera import KITTI_CAM0, CameraIntrinsics
from client.errors import InvalidInputError
from client.geometry import T_ZUP_FROM_KITTI, invert_rigid
from sim.camera import CameraConfig, Lighting
from sim.city import City, CityConfig, build_city
from sim.lidar import LidarConfig
from sim.recording import RecordingErrors
from sim.routes import lane_path, offset_path, plan_route, wandering_offset
from sim.vehicle import SensorRig, VehicleConfig, VehicleStates, drive

if TYPE_CHECKING:
    from sim.indoor_plan import IndoorConfig

RUN_KINDS = ("map", "query", "train", "night", "offcenter")
SCENARIOS = ("urban", "indoor")
FRAME_PERIOD_S = 0.1
CHUNK_FRAMES = 25


@dataclass(frozen=True)
class GenerateConfig:
    """What to generate. ``max_frames`` caps each run; ``image_scale`` resizes the camera
    (scaled intrinsics) for quick tests; ``write_depth`` adds sequences/NN/depth/.

    Scenario ``indoor`` (TUM RGB-D layout, ``sim.indoor_generate``) uses scenario, size,
    seed, runs (from map, query, train, offcenter; the default means all four),
    max_frames, image_scale, workers and ``indoor`` (default: the size preset;
    ``errors=RecordingErrors.none()`` also turns every indoor error off); the
    outdoor-only fields are ignored."""

    scenario: str = "urban"
    size: str = "small"
    seed: int = 0
    runs: tuple[str, ...] = RUN_KINDS
    max_frames: int | None = None
    image_scale: float = 1.0
    write_depth: bool = False
    write_lidar: bool = True
    query_lighting: str = "day"
    errors: RecordingErrors = field(default_factory=RecordingErrors)
    lidar: LidarConfig = field(default_factory=LidarConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    rig: SensorRig = field(default_factory=SensorRig)
    city: CityConfig | None = None
    query_max_offset_m: float = 1.5
    offcenter_steer_rad: float = 0.05
    workers: int = 1
    indoor: IndoorConfig | None = None

    def city_config(self) -> CityConfig:
        return self.city or CityConfig.preset(self.size)

    def intrinsics(self) -> CameraIntrinsics:
        if self.image_scale == 1.0:
            return KITTI_CAM0
        return KITTI_CAM0.scaled(self.image_scale)

    def validate(self) -> None:
        if self.scenario not in SCENARIOS:
            raise InvalidInputError(f"unknown scenario {self.scenario!r}; use one of {SCENARIOS}")
        kinds, runs = RUN_KINDS, self.runs
        if self.scenario == "indoor":
            from sim.indoor_plan import INDOOR_RUN_KINDS, indoor_runs

            kinds, runs = INDOOR_RUN_KINDS, indoor_runs(self.runs)
        bad = [r for r in runs if r not in kinds]
        if bad or not runs or len(set(runs)) != len(runs):
            raise InvalidInputError(
                f"{self.scenario} runs must be distinct names from {kinds}, got {runs}"
            )
        if self.max_frames is not None and self.max_frames < 1:
            raise InvalidInputError(f"max_frames must be >= 1, got {self.max_frames}")
        if not 0.05 <= self.image_scale <= 1.0:
            raise InvalidInputError(f"image_scale must be in [0.05, 1], got {self.image_scale}")
        if self.scenario == "indoor":
            from sim.indoor import room_configs

            room_configs(self.size) if self.indoor is None else None
            return
        CityConfig.preset(self.size) if self.city is None else None
        Lighting.preset(self.query_lighting)


@dataclass(frozen=True)
class RunPlan:
    """One run, fully decided before rendering: its drive (true states) and settings."""

    seq_id: str
    kind: str
    district: str
    lighting: Lighting
    car_variant: int
    seed: int
    states: VehicleStates
    frame_times_s: np.ndarray  # (n,) times in the drive
    route_length_m: float


@dataclass(frozen=True)
class SequenceSummary:
    seq_id: str
    kind: str
    lighting: str
    frames: int
    length_m: float


@dataclass(frozen=True)
class DatasetSummary:
    root: Path
    sequences: list[SequenceSummary]
    seconds: float


def _run_rng(seed: int, kind: str, purpose: int) -> np.random.Generator:
    return np.random.default_rng([seed, RUN_KINDS.index(kind), purpose])


def plan_runs(city: City, config: GenerateConfig) -> list[RunPlan]:
    """Routes, drives and settings of every run (cheap: no rendering)."""
    seed = config.seed
    main = city.grids["main"]
    route_rng = np.random.default_rng([seed, 100])
    main_path = lane_path(main, plan_route(main, route_rng))
    max_duration = None
    if config.max_frames is not None:
        max_duration = (config.max_frames + 2) * FRAME_PERIOD_S
    plans = []
    map_lighting = Lighting.preset("day", _run_rng(seed, "map", 1))
    for n, kind in enumerate(config.runs):
        rng = _run_rng(seed, kind, 2)
        path, target, vehicle, district = main_path, None, config.vehicle, "main"
        lighting, variant = map_lighting, 0
        if kind in ("query", "night"):
            offsets = wandering_offset(path, rng, config.query_max_offset_m)
            target = offset_path(path, offsets)
            variant = 1 if kind == "query" else 2
            lighting = Lighting.preset(
                config.query_lighting if kind == "query" else "night", _run_rng(seed, kind, 1)
            )
        elif kind == "offcenter":
            vehicle = replace(vehicle, steer_disturbance_rad=config.offcenter_steer_rad)
        elif kind == "train":
            train = city.grids["train"]
            path = lane_path(train, plan_route(train, np.random.default_rng([seed, 101])))
            district = "train"
            lighting = Lighting.preset("day", _run_rng(seed, kind, 1))
        states = drive(path, vehicle, rng, max_duration_s=max_duration, target=target)
        times = np.arange(FRAME_PERIOD_S, states.duration_s - FRAME_PERIOD_S, FRAME_PERIOD_S)
        if config.max_frames is not None:
            times = times[: config.max_frames]
        if len(times) == 0:
            raise InvalidInputError(f"run {kind!r} is too short to record a frame")
        plans.append(
            RunPlan(
                f"{n:02d}",
                kind,
                district,
                lighting,
                variant,
                int(np.random.default_rng([seed, 200, n]).integers(2**31)),
                states,
                times,
                path.length_m,
            )
        )
    return plans


def true_camera_poses(plan: RunPlan, rig: SensorRig) -> np.ndarray:
    """(n, 4, 4) true T_simworld_from_cam at the run's frame times."""
    return plan.states.T_world_from_vehicle(plan.frame_times_s) @ rig.T_vehicle_from_cam()


def kitti_world(T_simworld_from_cam0: np.ndarray) -> dict[str, np.ndarray]:
    """The dataset's world frames, given the (written) pose of the defining camera frame.

    ``T_simworld_from_kittiworld``: the KITTI world is that camera frame itself.
    ``T_simworld_from_zupworld``: the z-up world a reader gets from
    ``client.geometry.kitti_to_zup`` (T_zup = T_ZUP_FROM_KITTI @ T_kitti), i.e.
    T_simworld_from_kittiworld @ inv(T_ZUP_FROM_KITTI). This is the one place the sim's
    internal city frame is tied to the files' frames.
    """
    T_sk = np.asarray(T_simworld_from_cam0, dtype=np.float64)
    return {
        "T_simworld_from_kittiworld": T_sk,
        "T_simworld_from_zupworld": T_sk @ invert_rigid(T_ZUP_FROM_KITTI),
    }


def generate_dataset(
    config: GenerateConfig,
    out_dir: Path,
    progress: Callable[[str, int, int], None] | None = None,
) -> DatasetSummary:
    """Write the dataset under ``out_dir``; ``progress(seq_id, done, total)`` is called as
    frames are written."""
    from sim.generate_run import prepare_run_files, render_chunk, write_run_metadata

    config.validate()
    if config.scenario == "indoor":
        from sim.indoor_generate import generate_indoor_dataset

        return generate_indoor_dataset(config, out_dir, progress)
    start = time.perf_counter()
    out_dir = Path(out_dir)
    city = build_city(config.city_config(), config.seed)
    plans = plan_runs(city, config)
    written = {p.seq_id: prepare_run_files(p, config, out_dir) for p in plans}
    defining = next((p for p in plans if p.kind == "map"), plans[0])
    frames = kitti_world(written[defining.seq_id].T_written[0])
    for plan in plans:
        write_run_metadata(plan, written[plan.seq_id], frames, config, out_dir)
    jobs = [
        (plan, a, min(a + CHUNK_FRAMES, len(plan.frame_times_s)))
        for plan in plans
        for a in range(0, len(plan.frame_times_s), CHUNK_FRAMES)
    ]
    done = dict.fromkeys((p.seq_id for p in plans), 0)
    totals = {p.seq_id: len(p.frame_times_s) for p in plans}

    def report(plan, a, b):
        done[plan.seq_id] += b - a
        if progress is not None:
            progress(plan.seq_id, done[plan.seq_id], totals[plan.seq_id])

    if config.workers <= 1:
        for plan, a, b in jobs:
            render_chunk(config, plan, a, b, out_dir)
            report(plan, a, b)
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=config.workers, mp_context=ctx) as pool:
            futures = {
                pool.submit(render_chunk, config, plan, a, b, out_dir): (plan, a, b)
                for plan, a, b in jobs
            }
            from concurrent.futures import as_completed

            for fut in as_completed(futures):
                fut.result()
                report(*futures[fut])
    _write_dataset_json(config, plans, written, frames, out_dir)
    summaries = [
        SequenceSummary(p.seq_id, p.kind, p.lighting.name, len(p.frame_times_s), p.route_length_m)
        for p in plans
    ]
    return DatasetSummary(root=out_dir, sequences=summaries, seconds=time.perf_counter() - start)


def _matrix(T: np.ndarray) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.asarray(T)]


def _write_dataset_json(config, plans, written, frames, out_dir) -> None:
    from sim.kitti_writer import write_dataset_json

    k = config.intrinsics()
    info = {
        "format": "kitti-odometry",
        "generator": "monoloc sim",
        "scenario": config.scenario,
        "size": config.size,
        "seed": config.seed,
        "world_frame": (
            "All poses/NN.txt (T_world_from_cam0, 3x4 row-major) share one world frame: "
            "the camera-0 frame of the first frame of the map run as written (or of the "
            "first run if there is no map run), KITTI convention (x right, y down, z "
            "forward). client.geometry.kitti_to_zup converts it to monoloc's z-up world."
        ),
        "T_simworld_from_kittiworld": _matrix(frames["T_simworld_from_kittiworld"]),
        "T_simworld_from_zupworld": _matrix(frames["T_simworld_from_zupworld"]),
        "camera": {
            "fx": k.fx,
            "fy": k.fy,
            "cx": k.cx,
            "cy": k.cy,
            "width_px": k.width_px,
            "height_px": k.height_px,
        },
        "frame_period_s": FRAME_PERIOD_S,
        "rig": {
            "vehicle_frame": "origin on the ground below the rear axle, x forward, y left, "
            "z up; vehicle.txt speed is the rear axle's",
            "T_vehicle_from_cam0": _matrix(config.rig.T_vehicle_from_cam()),
            "T_vehicle_from_lidar": _matrix(config.rig.T_vehicle_from_lidar()),
            "T_cam0_from_lidar_true": _matrix(config.rig.T_cam_from_lidar()),
        },
        "lidar": asdict(config.lidar),
        "camera_model": asdict(config.camera),
        "recording_errors": config.errors.to_dict(),
        "depth": (
            "sequences/NN/depth/%06d.png: uint16 z-depth * 256, 0 = none"
            if config.write_depth
            else None
        ),
        "sequences": [
            {
                "id": p.seq_id,
                "run": p.kind,
                "scenario": config.scenario,
                "district": p.district,
                "seed": p.seed,
                "lighting": asdict(p.lighting),
                "parked_cars_variant": p.car_variant,
                "frames": len(p.frame_times_s),
                "route_length_m": round(p.route_length_m, 2),
                "T_cam0_from_lidar_written": _matrix(written[p.seq_id].Tr_written),
            }
            for p in plans
        ],
    }
    write_dataset_json(out_dir, info)


def frames_per_second_note(summary: DatasetSummary) -> str:
    n = sum(s.frames for s in summary.sequences)
    return f"{n} frames in {summary.seconds:.1f} s ({n / max(summary.seconds, 1e-9):.1f} fps)"

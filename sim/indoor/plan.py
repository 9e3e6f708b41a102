"""Settings of the indoor scenario and the plan of its runs (drives, clocks, lighting).

Runs (one TUM folder each, named after the run):

- ``map``: laps on the track's centre line.
- ``query``: the same laps later: smooth lateral offsets within +-0.2 m of the centre
  (the car stays inside the tape) with heading deviations up to ~6 deg, some obstacles
  moved, the lights a little different.
- ``train``: the training room (never seen by the others), its own track: a first lap
  on the centre line and further laps with query-like offsets, so a map built from one
  part and queries from another mimic map/query (the measurement-model calibration
  needs such a sequence that is not the test run).
- ``offcenter``: the map laps with a sinusoidal steering disturbance (map augmentation).

Clocks: the camera runs at ``frame_rate_hz`` (colour and depth, the depth stream's
stamps offset by a few ms per run, both jittered), the motion capture at
``mocap_rate_hz``; all stamps are on one Unix-like clock and every image is rendered at
its own stamp.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.sim.camera import CameraConfig, Lighting
from monoloc.sim.control import BicycleConfig
from monoloc.sim.indoor.camera_motion import (
    AutoExposureConfig,
    MotionBlurConfig,
    RollingShutterConfig,
)
from monoloc.sim.indoor.room import SIZE_PRESETS, RoomConfig, room_configs
from monoloc.sim.indoor.sensors import D435_COLOR, IndoorErrors, IndoorRig
from monoloc.sim.indoor.track import lap_length_m, lap_path
from monoloc.sim.indoor.world import IndoorWorld
from monoloc.sim.path import offset_path, wandering_offset
from monoloc.sim.render import RenderConfig
from monoloc.sim.vehicle import VehicleConfig, VehicleStates, drive

INDOOR_RUN_KINDS = ("map", "query", "train", "offcenter")
_OUTDOOR_DEFAULT_RUNS = ("map", "query", "train", "night", "offcenter")
# Query and training drives leave the centre line in swerves of 5 to 15 m of track.
SWERVE_WAVELENGTH_M = (5.0, 15.0)


def indoor_runs(runs: tuple[str, ...]) -> tuple[str, ...]:
    """The runs to generate: ``runs``, or all indoor runs for GenerateConfig's default
    (the outdoor list)."""
    return INDOOR_RUN_KINDS if tuple(runs) == _OUTDOOR_DEFAULT_RUNS else tuple(runs)


# A 1:10 car: 26 cm wheelbase, ~1 m/s, quick steering servo.
SCALE_CAR = VehicleConfig(
    wheelbase_m=0.26,
    speed_range_mps=(0.85, 1.15),
    max_lateral_accel=1.3,
    max_accel=1.0,
    max_decel=1.5,
    max_steer_rad=0.45,
    max_steer_rate_radps=4.0,
    lookahead_time_s=0.5,
    min_lookahead_m=0.35,
    dt_s=0.005,
    steer_disturbance_period_s=2.5,
    pitch_per_accel_rad=0.01,
    roll_per_lateral_accel_rad=0.01,
)
# The same car as the closed loop's bicycle (sim/control.py): its steering servo's limits,
# a 3 m/s top speed, 50 ms steering and 100 ms throttle lags.
SCALE_CAR_BICYCLE = BicycleConfig(
    wheelbase_m=SCALE_CAR.wheelbase_m,
    max_steer_rad=SCALE_CAR.max_steer_rad,
    max_steer_rate_radps=SCALE_CAR.max_steer_rate_radps,
    max_speed_mps=3.0,
    max_accel_mps2=SCALE_CAR.max_accel,
    max_decel_mps2=SCALE_CAR.max_decel,
    steer_lag_s=0.05,
    accel_lag_s=0.1,
)


@dataclass(frozen=True)
class IndoorConfig:
    """Everything the indoor runs depend on besides the seed (see the module docstring).
    ``motion_blur``, ``rolling_shutter`` and ``auto_exposure`` (its lag) act on
    closed-loop drives, which render frame after frame (``monoloc.sim.closed_loop_world``)."""

    main_room: RoomConfig = field(default_factory=RoomConfig)
    train_room: RoomConfig = field(default_factory=lambda: room_configs("small")["train"])
    laps: float = 1.0
    train_laps: float = 2.0
    frame_rate_hz: float = 15.0
    mocap_rate_hz: float = 200.0
    intrinsics: CameraIntrinsics = D435_COLOR
    rig: IndoorRig = field(default_factory=IndoorRig)
    vehicle: VehicleConfig = SCALE_CAR
    errors: IndoorErrors = field(default_factory=IndoorErrors)
    camera: CameraConfig = field(default_factory=lambda: CameraConfig(vignetting=0.3))
    render: RenderConfig = field(default_factory=lambda: RenderConfig(0.05, 25.0))
    query_max_offset_m: float = 0.2
    query_max_heading_rad: float = math.radians(6.0)
    offcenter_steer_rad: float = 0.25
    obstacle_change_fraction: float = 0.4
    motion_blur: MotionBlurConfig = field(default_factory=MotionBlurConfig)
    auto_exposure: AutoExposureConfig = field(default_factory=AutoExposureConfig)
    rolling_shutter: RollingShutterConfig = field(default_factory=RollingShutterConfig)

    @classmethod
    def preset(cls, size: str, errors: IndoorErrors | None = None) -> IndoorConfig:
        """small (8 x 6 m room, 1 lap per run), medium (10 x 7 m, 2 laps), large
        (12 x 9 m, twistier track, 3 laps)."""
        rooms = room_configs(size)
        laps = float(SIZE_PRESETS[size][1])
        return cls(
            main_room=rooms["main"],
            train_room=rooms["train"],
            laps=laps,
            train_laps=laps + 1.0,
            errors=errors if errors is not None else IndoorErrors(),
        )

    def rooms(self) -> dict[str, RoomConfig]:
        return {"main": self.main_room, "train": self.train_room}


def lab_lighting(rng: np.random.Generator, lamp: float = 3.0) -> Lighting:
    """Ceiling lamps and a little daylight from a random direction; no sky in a room.
    ``window_glow`` makes the lamp panels shine (their emission; the camera model calls
    any lighting with glow ``night``, which here only means "emission on")."""
    return Lighting(
        name="lab",
        sun_azimuth_rad=float(rng.uniform(-math.pi, math.pi)),
        sun_elevation_rad=float(rng.uniform(0.3, 0.7)),
        sun_strength=float(rng.uniform(0.05, 0.15)),
        ambient=float(rng.uniform(0.12, 0.18)),
        sky_horizon=1.0,
        sky_zenith=1.0,
        lamp_strength=lamp * float(rng.uniform(0.85, 1.15)),
        window_glow=0.6,
    )


@dataclass(frozen=True)
class IndoorRunPlan:
    """One run, decided before rendering. Times are drive times (s from the drive's
    start); a file stamp is ``stamp0_s`` + drive time."""

    run: str
    room: str
    lighting: Lighting
    obstacles_variant: int
    seed: int
    states: VehicleStates
    rgb_times_s: np.ndarray
    depth_times_s: np.ndarray
    mocap_times_s: np.ndarray
    stamp0_s: float
    laps: float
    route_length_m: float
    depth_offset_s: float


def _rng(seed: int, kind: str, purpose: int) -> np.random.Generator:
    return np.random.default_rng([seed, 1000 + INDOOR_RUN_KINDS.index(kind), purpose])


def plan_indoor_runs(
    world: IndoorWorld,
    config: IndoorConfig,
    runs: tuple[str, ...],
    seed: int,
    max_frames: int | None = None,
) -> list[IndoorRunPlan]:
    """Drives, clocks and settings of every run (cheap: no rendering)."""
    bad = [r for r in runs if r not in INDOOR_RUN_KINDS]
    if bad or not runs or len(set(runs)) != len(runs):
        raise InvalidInputError(
            f"indoor runs must be distinct names from {INDOOR_RUN_KINDS}, got {runs}"
        )
    period = 1.0 / config.frame_rate_hz
    max_duration = None if max_frames is None else max_frames * period + 1.0
    map_lighting = lab_lighting(_rng(seed, "map", 1))
    plans = []
    for n, kind in enumerate(runs):
        rng = _rng(seed, kind, 2)
        room = "train" if kind == "train" else "main"
        track = world.rooms[room].track
        laps = config.train_laps if kind == "train" else config.laps
        lead_out = 0.6 / lap_length_m(track)  # a little past the line, for the last frames
        path = lap_path(track, laps + lead_out)
        target, vehicle, lighting, variant = None, config.vehicle, map_lighting, 0
        if kind == "query":
            target = _offset(path, rng, config)
            lighting, variant = lab_lighting(_rng(seed, kind, 1)), 1
        elif kind == "train":
            offsets = wandering_offset(
                path,
                rng,
                config.query_max_offset_m,
                config.query_max_heading_rad,
                SWERVE_WAVELENGTH_M,
            )
            ramp = np.clip((path.s_m - lap_length_m(track)) / 2.0, 0.0, 1.0)  # from lap 2
            target = offset_path(path, offsets * ramp, step_m=0.02)
            lighting = lab_lighting(_rng(seed, kind, 1))
        elif kind == "offcenter":
            vehicle = replace(vehicle, steer_disturbance_rad=config.offcenter_steer_rad)
        states = drive(path, vehicle, rng, max_duration_s=max_duration, target=target)
        clock = _rng(seed, kind, 3)
        jitter = config.errors.stamp_jitter_s
        rgb = np.arange(0.3, states.duration_s - 0.2, period)
        if max_frames is not None:
            rgb = rgb[:max_frames]
        if len(rgb) == 0:
            raise InvalidInputError(f"run {kind!r} is too short to record a frame")
        rgb = rgb + clock.uniform(-jitter, jitter, len(rgb)) if jitter else rgb
        offset = config.errors.depth_time_offset_max_s
        offset = float(clock.uniform(-offset, offset)) if offset else 0.0
        depth = rgb + offset
        if jitter:
            depth = depth + clock.uniform(-jitter, jitter, len(depth))
        mocap_period = 1.0 / config.mocap_rate_hz
        mocap = np.arange(
            max(0.0, rgb[0] - 0.25) + clock.uniform(0, mocap_period),
            min(states.duration_s, rgb[-1] + 0.25),
            mocap_period,
        )
        stamp0 = 1_700_000_000.0 + 86_400.0 * (seed % 1000) + 900.0 * n
        plans.append(
            IndoorRunPlan(
                run=kind,
                room=room,
                lighting=lighting,
                obstacles_variant=variant,
                seed=int(np.random.default_rng([seed, 200, n]).integers(2**31)),
                states=states,
                rgb_times_s=rgb,
                depth_times_s=depth,
                mocap_times_s=mocap,
                stamp0_s=stamp0,
                laps=laps,
                route_length_m=path.length_m,
                depth_offset_s=offset,
            )
        )
    return plans


def _offset(path, rng, config: IndoorConfig):
    offsets = wandering_offset(
        path, rng, config.query_max_offset_m, config.query_max_heading_rad, SWERVE_WAVELENGTH_M
    )
    return offset_path(path, offsets, step_m=0.02)


def T_world_from_cam_at(plan: IndoorRunPlan, rig: IndoorRig, times_s: np.ndarray) -> np.ndarray:
    """(n, 4, 4) true camera poses at drive times ``times_s``."""
    return plan.states.T_world_from_vehicle(np.asarray(times_s)) @ rig.T_vehicle_from_cam()

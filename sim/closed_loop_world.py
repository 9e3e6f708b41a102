"""The worlds a closed-loop vehicle drives in: what it sees (rendered camera, depth when
mapping), the path it must follow, its lane, its vehicle and controller settings.

``IndoorLoopWorld``: the 1:10 car on the indoor race track (centre line as reference,
the taped track as the lane), an RGB-D camera (depth registered to colour), the
motion-capture frame as world (z up) - the same frame as the indoor dataset's
``groundtruth.txt``, so maps built from either agree.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.sim.camera import CameraConfig, Lighting, auto_exposure, expose, shade
from monoloc.sim.control import BicycleConfig, BicycleState, ControllerConfig
from monoloc.sim.path import Path
from monoloc.sim.render import rasterize


@dataclass(frozen=True)
class SignalErrors:
    """Errors of the vehicle's measured speed and yaw rate: a per-run scale factor and
    bias (drawn once, standard deviations given) and white noise per sample."""

    speed_scale_error: float = 0.01
    speed_bias_mps: float = 0.005
    speed_noise_mps: float = 0.02
    yaw_rate_bias_radps: float = 0.003
    yaw_rate_noise_radps: float = 0.01


@dataclass(frozen=True)
class Lap:
    """What one lap of a world looks like: which room/district, obstacles variant and
    lighting (map laps share the map's; query laps differ)."""

    room: str = "main"
    variant: int = 0
    lighting_key: int = 1  # 1: the map's lighting; other values draw another


def controller_config_for(world, disturbance: bool, phase_rad: float = 0.0) -> ControllerConfig:
    """The world's tracking controller: its reference speed and loop bandwidth, with or
    without its steering disturbance (the oscillating, off-center laps)."""
    config = ControllerConfig.for_vehicle(
        world.bicycle,
        world.reference_speed_mps,
        world.natural_freq_radps,
        world.disturbance_rad if disturbance else 0.0,
        world.disturbance_period_s,
    )
    return replace(config, disturbance_phase_rad=phase_rad)


class IndoorLoopWorld:
    """The indoor scenario of ``monoloc.sim.indoor`` for closed-loop driving."""

    name = "indoor"
    run_format = "tum"

    def __init__(
        self,
        size: str = "small",
        seed: int = 0,
        sensor_noise: bool = True,
        bare_end: bool = True,
        near_clutter: bool = True,
    ) -> None:
        """``bare_end`` False: the rooms without their featureless end; ``near_clutter``
        False: without the chairs, stands and legs beside the tape (RoomConfig)."""
        from monoloc.sim.indoor.plan import SCALE_CAR, SCALE_CAR_BICYCLE, IndoorConfig
        from monoloc.sim.indoor.room import NearClutterConfig
        from monoloc.sim.indoor.sensors import IndoorErrors
        from monoloc.sim.indoor.world import build_world

        self.seed = seed
        self.config = IndoorConfig.preset(size)
        if not bare_end:
            self.config = replace(
                self.config,
                main_room=replace(self.config.main_room, featureless_end_m=0.0),
                train_room=replace(self.config.train_room, featureless_end_m=0.0),
            )
        if not near_clutter:
            none = NearClutterConfig(items=0)
            self.config = replace(
                self.config,
                main_room=replace(self.config.main_room, near_clutter=none),
                train_room=replace(self.config.train_room, near_clutter=none),
            )
        self.world = build_world(self.config.rooms(), seed)
        self.sensor_noise = sensor_noise
        rig = self.config.rig
        self.T_vehicle_from_cam = rig.T_vehicle_from_cam()
        self.lever_arm_m = rig.camera_ahead_of_rear_axle_m
        self.intrinsics: CameraIntrinsics = self.config.intrinsics
        from monoloc.sim.indoor.sensors import calibrated_intrinsics, hand_eye_residual

        # One calibration per rig (world seed): what every run's camera.json and tracker
        # poses carry (the true intrinsics render).
        errors = self.config.errors if sensor_noise else IndoorErrors.none()
        rig_rng = np.random.default_rng([seed, 43])
        self.T_cam_from_recorded = hand_eye_residual(errors, rig_rng)
        self.calibrated_intrinsics = calibrated_intrinsics(self.intrinsics, errors, rig_rng)
        self.frame_rate_hz = self.config.frame_rate_hz
        self.dt_s = SCALE_CAR.dt_s
        self.bicycle = SCALE_CAR_BICYCLE
        self.reference_speed_mps = 1.0
        self.natural_freq_radps = 2.0
        # The paper's oscillating laps: SCALE_CAR's off-center disturbance and period.
        self.disturbance_rad = self.config.offcenter_steer_rad
        self.disturbance_period_s = SCALE_CAR.steer_disturbance_period_s
        car_half_width_m = 0.1
        self.lane_half_width_m = self.config.main_room.track_width_m / 2 - car_half_width_m
        self.signal_errors = SignalErrors(
            speed_scale_error=self.config.errors.speed_scale_error,
            speed_bias_mps=self.config.errors.speed_bias_mps,
            speed_noise_mps=self.config.errors.speed_noise_mps,
            yaw_rate_bias_radps=self.config.errors.yaw_rate_bias_radps,
            yaw_rate_noise_radps=self.config.errors.yaw_rate_noise_radps,
        )
        self._scenes: dict = {}
        self._bank = None
        from monoloc.sim.indoor.camera_motion import CameraState

        self.camera_state = CameraState()

    def reference_path(self, laps: float, room: str = "main") -> Path:
        """The track's centre line driven ``laps`` times from the start line, plus a
        lead-out so the last frames still have path ahead."""
        from monoloc.sim.indoor.track import lap_length_m, lap_path

        track = self.world.rooms[room].track
        return lap_path(track, laps + 1.0 / lap_length_m(track))

    def controller_config(self, disturbance: bool, phase_rad: float = 0.0) -> ControllerConfig:
        return controller_config_for(self, disturbance, phase_rad)

    def start_state(self, path: Path) -> BicycleState:
        x, y = path.xy[0]
        return BicycleState(
            float(x), float(y), float(path.heading_rad[0]), self.reference_speed_mps
        )

    def lighting(self, lap: Lap) -> Lighting:
        """The lap's lighting; a drive asks for it once, at its start, so the camera's
        frame-to-frame state (motion, exposure) starts afresh here."""
        from monoloc.sim.indoor.plan import lab_lighting

        self.camera_state.reset()
        # Key 1 is the map run's lighting in monoloc.sim.indoor.plan (seed, 1000 + 0, 1).
        return lab_lighting(np.random.default_rng([self.seed, 1000, lap.lighting_key]))

    def camera_config(self) -> CameraConfig:
        cam = self.config.camera
        if not self.sensor_noise:
            cam = replace(cam, shot_noise=0.0, read_noise=0.0)
        return cam

    def _scene(self, lap: Lap):
        from monoloc.sim.indoor.infield import obstacles_scene
        from monoloc.sim.indoor.textures import INDOOR_TEXTURES
        from monoloc.sim.scene import concat_scenes
        from monoloc.sim.textures import TextureBank

        if lap.room not in self.world.rooms:
            raise InvalidInputError(f"no room {lap.room!r}; use one of {sorted(self.world.rooms)}")
        if self._bank is None:
            self._bank = TextureBank(INDOOR_TEXTURES, max_bytes=600_000_000)
        key = (lap.room, lap.variant)
        if key not in self._scenes:
            room = self.world.rooms[lap.room]
            obstacles = obstacles_scene(
                room.slots,
                self.seed * 1009 + (lap.room == "train"),
                lap.variant,
                change_fraction=self.config.obstacle_change_fraction,
            )
            self._scenes[key] = concat_scenes([room.static, obstacles])
        return self._scenes[key], self._bank

    def render(
        self,
        lap: Lap,
        lighting: Lighting,
        T_world_from_cam: np.ndarray,
        rng: np.random.Generator,
        with_depth: bool,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Grayscale image (H, W) uint8 seen from ``T_world_from_cam``; with
        ``with_depth`` also the depth the RGB-D sensor reports (H, W) float32 m (0: none),
        registered to the image. Frames of one drive come one frame period apart: the
        exposure follows the scene's brightness with its lag, and the image is blurred
        by the motion since the previous frame over the exposure time."""
        from monoloc.sim.indoor.camera_motion import motion_blur, rolling_shutter
        from monoloc.sim.indoor.sensors import noisy_depth

        scene, bank = self._scene(lap)
        raster = rasterize(
            scene, bank, T_world_from_cam, self.intrinsics, self.config.render, night=lighting.night
        )
        radiance = shade(raster, scene, T_world_from_cam, self.intrinsics, lighting)
        cam = self.camera_config()
        state = self.camera_state
        period_s = 1.0 / self.frame_rate_hz
        cam = replace(cam, adaptation=state.adaptation(self.config.auto_exposure, period_s))
        exposure = auto_exposure(radiance, cam, state.exposure)
        blur = self.config.motion_blur
        readout_s = self.config.rolling_shutter.readout_s
        if state.T_world_from_cam is not None and (blur.enabled or readout_s > 0):
            T_prev_from_cur = np.linalg.inv(state.T_world_from_cam) @ T_world_from_cam
            if readout_s > 0:
                radiance = rolling_shutter(
                    radiance, raster.depth_m, T_prev_from_cur, self.intrinsics,
                    readout_s / period_s,
                )  # fmt: skip
            if blur.enabled:
                share = min(exposure, cam.max_exposure) / cam.max_exposure
                radiance = motion_blur(
                    radiance, raster.depth_m, T_prev_from_cur, self.intrinsics,
                    blur.max_exposure_time_s * share / period_s, blur.samples,
                )  # fmt: skip
        state.T_world_from_cam, state.exposure = np.array(T_world_from_cam), exposure
        image = expose(radiance, exposure, cam, rng)
        if not with_depth:
            return image, None
        return image, noisy_depth(raster.depth_m, image, self.config.errors.depth, rng)

    def tracker_poses(
        self,
        T_world_from_cam: np.ndarray,
        rng: np.random.Generator,
        t_s: np.ndarray | None = None,
    ) -> np.ndarray:
        """(n, 4, 4) the poses a run's ground truth records for its true camera poses
        (n, 4, 4) at times ``t_s`` (n,) s: one clock offset later, through the rig's
        hand-eye residual, with the tracker's jitter and per-run bias
        (``sensors.recorded_truth``; exact without sensor noise)."""
        from monoloc.sim.indoor.sensors import recorded_truth

        if not self.sensor_noise:
            return np.asarray(T_world_from_cam)
        return recorded_truth(
            T_world_from_cam, t_s, self.config.errors, self.T_cam_from_recorded, rng
        )

    def camera_json_extra(self) -> dict:
        return {
            "world_frame": "z-up",
            "depth_registered_to": "rgb",
            "T_vehicle_from_cam": [[float(v) for v in row] for row in self.T_vehicle_from_cam],
        }


class UrbanLoopWorld:
    """The KITTI-like city of ``monoloc.sim.urban`` for closed-loop driving: the main
    district's route in the right-hand lane's centre (the map run's route) as reference,
    the lane as the lane, the KITTI-like rig (camera + LiDAR when mapping). The route is
    not a loop: ``laps`` is the share of it driven (at most 1). Runs are written in the
    KITTI layout with poses such that the server's z-up world is the sim's world."""

    name = "urban"
    run_format = "kitti"

    def __init__(self, size: str = "small", seed: int = 0, sensor_noise: bool = True) -> None:
        from monoloc.sim.generate import GenerateConfig
        from monoloc.sim.urban.city import build_city
        from monoloc.sim.urban.runs import FRAME_PERIOD_S

        self.seed = seed
        self.config = GenerateConfig(size=size, seed=seed)
        self.city = build_city(self.config.city_config(), seed)
        self.sensor_noise = sensor_noise
        rig = self.config.rig
        self.T_vehicle_from_cam = rig.T_vehicle_from_cam()
        self.T_cam_from_lidar = rig.T_cam_from_lidar()
        self.lever_arm_m = rig.camera_ahead_of_rear_axle_m
        self.intrinsics: CameraIntrinsics = self.config.intrinsics()
        self.calibrated_intrinsics = self.intrinsics  # the sim's city camera: as calibrated
        self.frame_rate_hz = 1.0 / FRAME_PERIOD_S
        vehicle = self.config.vehicle
        self.dt_s = vehicle.dt_s
        self.bicycle = BicycleConfig(
            wheelbase_m=vehicle.wheelbase_m,
            max_steer_rad=vehicle.max_steer_rad,
            max_steer_rate_radps=vehicle.max_steer_rate_radps,
            max_speed_mps=20.0,
            max_accel_mps2=vehicle.max_accel,
            max_decel_mps2=vehicle.max_decel,
            steer_lag_s=0.1,
            accel_lag_s=0.2,
        )
        # City streets at a constant 18 km/h: the route's 6 m right turns stay drivable.
        self.reference_speed_mps = 5.0
        self.natural_freq_radps = 0.8
        self.disturbance_rad = self.config.offcenter_steer_rad
        self.disturbance_period_s = vehicle.steer_disturbance_period_s
        car_half_width_m = 0.9
        self.lane_half_width_m = self.config.city_config().lane_width_m / 2 - car_half_width_m
        e = self.config.errors
        self.signal_errors = SignalErrors(
            speed_scale_error=e.speed_scale_error,
            speed_bias_mps=e.speed_bias_mps,
            speed_noise_mps=e.speed_noise_mps,
            yaw_rate_bias_radps=e.yaw_rate_bias_radps,
            yaw_rate_noise_radps=e.yaw_rate_noise_radps,
        )
        self._scenes: dict = {}
        self._bank = None

    def reference_path(self, laps: float, room: str = "main") -> Path:
        from monoloc.sim.urban.routes import lane_path, plan_route

        if room not in self.city.grids:
            raise InvalidInputError(f"no district {room!r}; use one of {sorted(self.city.grids)}")
        if laps > 1.0:
            raise InvalidInputError("a city route is not a loop: laps must be at most 1")
        grid = self.city.grids[room]
        key = 100 if room == "main" else 101  # the map / train runs' routes
        path = lane_path(grid, plan_route(grid, np.random.default_rng([self.seed, key])))
        keep = path.s_m <= laps * path.length_m + 1e-9
        return Path(path.xy[keep], path.heading_rad[keep], path.curvature[keep], path.s_m[keep])

    def controller_config(self, disturbance: bool, phase_rad: float = 0.0) -> ControllerConfig:
        return controller_config_for(self, disturbance, phase_rad)

    def start_state(self, path: Path) -> BicycleState:
        x, y = path.xy[0]
        return BicycleState(
            float(x), float(y), float(path.heading_rad[0]), self.reference_speed_mps
        )

    def lighting(self, lap: Lap) -> Lighting:
        # Key 1 is the map run's day lighting in monoloc.sim.urban.runs (seed, 0, 1).
        return Lighting.preset("day", np.random.default_rng([self.seed, 0, lap.lighting_key]))

    def _scene(self, lap: Lap):
        from monoloc.sim.scene import concat_scenes
        from monoloc.sim.textures import TextureBank
        from monoloc.sim.urban.city import parked_cars
        from monoloc.sim.urban.textures import URBAN_TEXTURES

        if self._bank is None:
            self._bank = TextureBank(URBAN_TEXTURES, max_bytes=700_000_000)
        if lap.variant not in self._scenes:
            self._scenes[lap.variant] = concat_scenes(
                [self.city.static, parked_cars(self.city, lap.variant)]
            )
        return self._scenes[lap.variant], self._bank

    def render(
        self,
        lap: Lap,
        lighting: Lighting,
        T_world_from_cam: np.ndarray,
        rng: np.random.Generator,
        with_depth: bool,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Grayscale image (H, W) uint8; with ``with_depth`` also the LiDAR sweep (N, 4)
        float32 (x, y, z, reflectance in the LiDAR frame) from the same pose."""
        from monoloc.sim.camera import render
        from monoloc.sim.lidar import scan

        scene, bank = self._scene(lap)
        cam = self.config.camera
        if not self.sensor_noise:
            cam = replace(cam, shot_noise=0.0, read_noise=0.0)
        frame = render(scene, bank, T_world_from_cam, self.intrinsics, lighting, rng, cam)
        if not with_depth:
            return frame.image, None
        T_world_from_lidar = T_world_from_cam @ self.T_cam_from_lidar
        return frame.image, scan(scene, T_world_from_lidar, self.config.lidar, rng, bank)

    def camera_json_extra(self) -> dict:
        return {"world_frame": "z-up"}


@dataclass
class WorldSpec:
    """How to build a world by name (CLI, bench)."""

    scenario: str = "indoor"
    size: str = "small"
    seed: int = 0
    options: dict = field(default_factory=dict)


def build_loop_world(spec: WorldSpec):
    if spec.scenario == "indoor":
        return IndoorLoopWorld(spec.size, spec.seed, **spec.options)
    if spec.scenario == "urban":
        return UrbanLoopWorld(spec.size, spec.seed, **spec.options)
    raise InvalidInputError(
        f"closed-loop scenario {spec.scenario!r} is not available; use indoor or urban"
    )


def planar_from_vehicle(x_m: float, y_m: float, yaw_rad: float, lever_arm_m: float) -> np.ndarray:
    """Camera planar pose (X, Y, psi) of a level vehicle whose camera sits ``lever_arm_m``
    ahead of the rear axle."""
    return np.array(
        [x_m + lever_arm_m * math.cos(yaw_rad), y_m + lever_arm_m * math.sin(yaw_rad), yaw_rad]
    )


def vehicle_from_planar(pose_world: np.ndarray, lever_arm_m: float) -> tuple[float, float, float]:
    """Rear-axle (x, y, yaw) of a camera planar pose (inverse of planar_from_vehicle)."""
    x, y, psi = (float(v) for v in pose_world)
    return x - lever_arm_m * math.cos(psi), y - lever_arm_m * math.sin(psi), psi

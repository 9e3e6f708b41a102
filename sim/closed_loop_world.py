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


class IndoorLoopWorld:
    """The indoor scenario of ``monoloc.sim.indoor`` for closed-loop driving."""

    name = "indoor"

    def __init__(self, size: str = "small", seed: int = 0, sensor_noise: bool = True) -> None:
        from monoloc.sim.indoor.plan import SCALE_CAR, IndoorConfig
        from monoloc.sim.indoor.world import build_world

        self.seed = seed
        self.config = IndoorConfig.preset(size)
        self.world = build_world(self.config.rooms(), seed)
        self.sensor_noise = sensor_noise
        rig = self.config.rig
        self.T_vehicle_from_cam = rig.T_vehicle_from_cam()
        self.lever_arm_m = rig.camera_ahead_of_rear_axle_m
        self.intrinsics: CameraIntrinsics = self.config.intrinsics
        self.frame_rate_hz = self.config.frame_rate_hz
        self.dt_s = SCALE_CAR.dt_s
        self.bicycle = BicycleConfig(
            wheelbase_m=SCALE_CAR.wheelbase_m,
            max_steer_rad=SCALE_CAR.max_steer_rad,
            max_steer_rate_radps=SCALE_CAR.max_steer_rate_radps,
            max_speed_mps=3.0,
            max_accel_mps2=SCALE_CAR.max_accel,
            max_decel_mps2=SCALE_CAR.max_decel,
            steer_lag_s=0.05,
            accel_lag_s=0.1,
        )
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

    def reference_path(self, laps: float, room: str = "main") -> Path:
        """The track's centre line driven ``laps`` times from the start line, plus a
        lead-out so the last frames still have path ahead."""
        from monoloc.sim.indoor.track import lap_length_m, lap_path

        track = self.world.rooms[room].track
        return lap_path(track, laps + 1.0 / lap_length_m(track))

    def controller_config(self, disturbance: bool, phase_rad: float = 0.0) -> ControllerConfig:
        config = ControllerConfig.for_vehicle(
            self.bicycle,
            self.reference_speed_mps,
            self.natural_freq_radps,
            self.disturbance_rad if disturbance else 0.0,
            self.disturbance_period_s,
        )
        return replace(config, disturbance_phase_rad=phase_rad)

    def start_state(self, path: Path) -> BicycleState:
        x, y = path.xy[0]
        return BicycleState(
            float(x), float(y), float(path.heading_rad[0]), self.reference_speed_mps
        )

    def lighting(self, lap: Lap) -> Lighting:
        from monoloc.sim.indoor.plan import lab_lighting

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
        registered to the image."""
        from monoloc.sim.indoor.sensors import noisy_depth

        scene, bank = self._scene(lap)
        raster = rasterize(
            scene, bank, T_world_from_cam, self.intrinsics, self.config.render, night=lighting.night
        )
        radiance = shade(raster, scene, T_world_from_cam, self.intrinsics, lighting)
        cam = self.camera_config()
        image = expose(radiance, auto_exposure(radiance, cam), cam, rng)
        if not with_depth:
            return image, None
        return image, noisy_depth(raster.depth_m, image, self.config.errors.depth, rng)

    def camera_json_extra(self) -> dict:
        return {
            "world_frame": "z-up",
            "depth_registered_to": "rgb",
            "T_vehicle_from_cam": [[float(v) for v in row] for row in self.T_vehicle_from_cam],
        }


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
    raise InvalidInputError(
        f"closed-loop scenario {spec.scenario!r} is not available; use 'indoor'"
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

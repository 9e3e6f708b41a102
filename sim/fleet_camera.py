"""A fleet car's camera that is not the mapping car's (issue 48): its own image size,
focal length, lens distortion and mounting on the vehicle.

The ``fleet`` run of an urban dataset is the ``query`` drive recorded by this camera
(``monoloc.sim.urban.runs``): same route, swerves, lighting and parked cars, so its
figures stand beside the mapping camera's frame for frame. Its files carry the camera
as a vehicle's recording would: calib.txt's P0 (K), a ``camera.json`` beside the frames
(fx, fy, cx, cy, width, height, distortion_model, D in ROS CameraInfo's order) and its
truth poses are the fleet camera's own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from monoloc.core.camera import CameraIntrinsics, LensDistortion
from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import R_world_from_cam_level


@dataclass(frozen=True)
class FleetCameraConfig:
    """Intrinsics (pixels; ``cx``/``cy`` None: the image centre), lens (``distortion_model``
    and ``distortion`` D; model None: a pinhole) and mounting relative to the mapping
    camera of the rig (``monoloc.sim.vehicle.SensorRig``): ``ahead_m`` / ``left_m`` /
    ``above_m`` its lever arm in the vehicle frame (x forward, y left, z up),
    ``pitch_down_rad`` the optical axis tilted towards the road, ``yaw_left_rad`` turned
    counter-clockwise seen from above, ``roll_rad`` about the optical axis (clockwise in
    the image)."""

    name: str = "issue48"
    width_px: int = 1024
    height_px: int = 576
    focal_px: float = 640.0
    cx: float | None = None
    cy: float | None = None
    distortion_model: str | None = "plumb_bob"
    distortion: tuple[float, ...] = (-0.28, 0.09, 0.0006, -0.0004)
    ahead_m: float = 0.0
    left_m: float = 0.0
    above_m: float = -0.23
    pitch_down_rad: float = math.radians(3.0)
    yaw_left_rad: float = math.radians(0.8)
    roll_rad: float = 0.0

    @classmethod
    def preset(cls, name: str) -> FleetCameraConfig:
        """One of :data:`FLEET_CAMERAS`."""
        if name not in FLEET_CAMERAS:
            raise InvalidInputError(
                f"unknown fleet camera {name!r}; use one of {sorted(FLEET_CAMERAS)}"
            )
        return FLEET_CAMERAS[name]

    def validate(self) -> None:
        self.intrinsics()  # CameraIntrinsics and LensDistortion check their values
        angles = (self.pitch_down_rad, self.yaw_left_rad, self.roll_rad)
        if not all(math.isfinite(a) and abs(a) < math.radians(30) for a in angles):
            raise InvalidInputError(f"mounting angles must be within 30 deg, got {angles} rad")
        arm = (self.ahead_m, self.left_m, self.above_m)
        if not all(math.isfinite(v) and abs(v) <= 3.0 for v in arm):
            raise InvalidInputError(f"lever arm must be within 3 m of the mapping camera: {arm}")

    @property
    def lens(self) -> LensDistortion | None:
        return LensDistortion.parse(self.distortion_model, self.distortion)

    def intrinsics(self, image_scale: float = 1.0) -> CameraIntrinsics:
        """The camera (with its lens), resized by ``image_scale`` (quick tests)."""
        cx = (self.width_px - 1) / 2 if self.cx is None else self.cx
        cy = (self.height_px - 1) / 2 if self.cy is None else self.cy
        camera = CameraIntrinsics(
            self.focal_px, self.focal_px, cx, cy, self.width_px, self.height_px, self.lens
        )
        return camera if image_scale == 1.0 else camera.scaled(image_scale)

    def T_mapcam_from_cam(self) -> np.ndarray:
        """(4, 4) this camera in the mapping camera's frame (OpenCV axes, level mount)."""
        R_vehicle_from_mapcam = R_world_from_cam_level(0.0)
        R_vehicle_from_cam = R_world_from_cam_level(
            self.yaw_left_rad, -self.pitch_down_rad, self.roll_rad
        )
        T = np.eye(4)
        T[:3, :3] = R_vehicle_from_mapcam.T @ R_vehicle_from_cam
        T[:3, 3] = R_vehicle_from_mapcam.T @ np.array([self.ahead_m, self.left_m, self.above_m])
        return T

    def T_vehicle_from_cam(self, T_vehicle_from_mapcam: np.ndarray) -> np.ndarray:
        """(4, 4) this camera on the vehicle, given the rig's mapping camera."""
        return np.asarray(T_vehicle_from_mapcam) @ self.T_mapcam_from_cam()


# issue 48's fleet camera; its fisheye sibling (an equidistant lens of wider view on the
# same mounting); and the same camera without its lens (a rectified stream)
FLEET_CAMERAS: dict[str, FleetCameraConfig] = {
    "issue48": FleetCameraConfig(),
    "issue48_equidistant": FleetCameraConfig(
        name="issue48_equidistant",
        focal_px=520.0,
        distortion_model="equidistant",
        distortion=(0.06, -0.02, 0.004, -0.001),
    ),
    "issue48_pinhole": FleetCameraConfig(
        name="issue48_pinhole", distortion_model=None, distortion=()
    ),
}


def without_lens(config: FleetCameraConfig) -> FleetCameraConfig:
    """The same camera and mounting as an ideal pinhole."""
    return replace(config, name=f"{config.name}_pinhole", distortion_model=None, distortion=())

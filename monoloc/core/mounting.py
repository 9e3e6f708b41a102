"""How a camera sits on its vehicle: ``T_vehicle_from_cam``.

Frames. The vehicle frame has its origin at the point whose speed the vehicle measures
(the rear axle's centre on a car: the point that moves along the vehicle's heading), x
forward, y left, z up (ROS's ``base_link``). The camera frame is OpenCV's (x right, y
down, z forward). A camera looking straight ahead, level, is the nominal mounting
``R_vehicle_from_cam = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]``; the mounting's rotation is
the nominal one turned by roll (about the vehicle's x), then pitch (about its y:
positive looks down), then yaw (about its z: positive looks left):
``R_vehicle_from_cam = Rz(yaw) Ry(pitch) Rx(roll) R_nominal``.

What the planar filter needs is the camera's planar pose in the vehicle frame
(:class:`PlanarMount`: ``x_m`` ahead, ``y_m`` left, ``yaw_rad`` the heading of the optical
axis from the vehicle's x): with this rotation order the optical axis' heading offset is
exactly ``yaw_rad`` whatever roll and pitch are. Height, pitch and roll do not move the
camera's planar pose; they give the vehicle's height from the camera's and the full
transform for whoever needs it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import check_rigid, wrap_angle

R_VEHICLE_FROM_CAM_NOMINAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class PlanarMount:
    """The camera's planar pose in the vehicle frame: ``x_m`` ahead of the reference
    point, ``y_m`` to its left, ``yaw_rad`` the optical axis' heading from the vehicle's
    x (counter-clockwise)."""

    x_m: float = 0.0
    y_m: float = 0.0
    yaw_rad: float = 0.0

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (self.x_m, self.y_m, self.yaw_rad)):
            raise InvalidInputError(f"a camera mounting must be finite, got {self}")

    @property
    def is_zero(self) -> bool:
        return self.x_m == 0.0 and self.y_m == 0.0 and self.yaw_rad == 0.0

    def vehicle_from_camera(self, camera_world: np.ndarray) -> np.ndarray:
        """Vehicle planar poses (N, 3) of camera planar poses (N, 3) (or (3,))."""
        cam = np.asarray(camera_world, dtype=np.float64)
        flat = cam.ndim == 1
        cam = np.atleast_2d(cam)
        psi_v = cam[:, 2] - self.yaw_rad
        c, s = np.cos(psi_v), np.sin(psi_v)
        out = np.empty_like(cam)
        out[:, 0] = cam[:, 0] - (c * self.x_m - s * self.y_m)
        out[:, 1] = cam[:, 1] - (s * self.x_m + c * self.y_m)
        out[:, 2] = wrap_angle(psi_v)
        return out[0] if flat else out

    def camera_from_vehicle(self, vehicle_world: np.ndarray) -> np.ndarray:
        """Camera planar poses (N, 3) of vehicle planar poses (N, 3) (or (3,))."""
        veh = np.asarray(vehicle_world, dtype=np.float64)
        flat = veh.ndim == 1
        veh = np.atleast_2d(veh)
        c, s = np.cos(veh[:, 2]), np.sin(veh[:, 2])
        out = np.empty_like(veh)
        out[:, 0] = veh[:, 0] + c * self.x_m - s * self.y_m
        out[:, 1] = veh[:, 1] + s * self.x_m + c * self.y_m
        out[:, 2] = wrap_angle(veh[:, 2] + self.yaw_rad)
        return out[0] if flat else out


@dataclass(frozen=True)
class CameraMounting:
    """``T_vehicle_from_cam`` by its parts (module docstring): the camera ``lever_arm_m``
    ahead of the vehicle's reference point, ``lateral_m`` to its left, ``height_m`` above
    it; turned by ``roll_rad``, ``pitch_rad`` (positive: looking down) and ``yaw_rad``
    (positive: looking left) from looking straight ahead, level."""

    lever_arm_m: float = 0.0
    lateral_m: float = 0.0
    height_m: float = 0.0
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float = 0.0

    def __post_init__(self) -> None:
        values = (
            self.lever_arm_m,
            self.lateral_m,
            self.height_m,
            self.roll_rad,
            self.pitch_rad,
            self.yaw_rad,
        )
        if not all(math.isfinite(float(v)) for v in values):
            raise InvalidInputError(f"a camera mounting must be finite, got {self}")
        if abs(self.pitch_rad) >= math.pi / 2:
            raise InvalidInputError(
                f"pitch_rad {self.pitch_rad} is not below 90 degrees: the camera must look "
                "ahead, not up or down"
            )

    @property
    def R_vehicle_from_cam(self) -> np.ndarray:
        turn = _rot_z(self.yaw_rad) @ _rot_y(self.pitch_rad) @ _rot_x(self.roll_rad)
        return turn @ R_VEHICLE_FROM_CAM_NOMINAL

    @property
    def T_vehicle_from_cam(self) -> np.ndarray:
        """(4, 4) float64: camera-frame points to vehicle-frame points."""
        T = np.eye(4)
        T[:3, :3] = self.R_vehicle_from_cam
        T[:3, 3] = [self.lever_arm_m, self.lateral_m, self.height_m]
        return T

    @property
    def planar(self) -> PlanarMount:
        """What the planar filter uses: the camera's planar pose in the vehicle frame."""
        return PlanarMount(self.lever_arm_m, self.lateral_m, self.yaw_rad)

    @classmethod
    def from_T_vehicle_from_cam(cls, T_vehicle_from_cam: np.ndarray) -> CameraMounting:
        """The parts of a rigid ``T_vehicle_from_cam`` (InvalidInputError if it is not
        rigid, or its camera looks up or down more than ahead)."""
        T = check_rigid(np.asarray(T_vehicle_from_cam, dtype=np.float64), "T_vehicle_from_cam")
        turn = T[:3, :3] @ R_VEHICLE_FROM_CAM_NOMINAL.T  # Rz(yaw) Ry(pitch) Rx(roll)
        pitch = math.asin(float(np.clip(-turn[2, 0], -1.0, 1.0)))
        if abs(math.cos(pitch)) < 1e-6:
            raise InvalidInputError("T_vehicle_from_cam: the camera looks straight up or down")
        yaw = math.atan2(turn[1, 0], turn[0, 0])
        roll = math.atan2(turn[2, 1], turn[2, 2])
        x, y, z = (float(v) for v in T[:3, 3])
        return cls(x, y, z, roll, pitch, yaw)

    @classmethod
    def from_dict(cls, data: dict) -> CameraMounting:
        """From ``T_vehicle_from_cam`` (4x4 rows, 16 values row-major, or ROS's
        ``{rows, cols, data}``) or the parts' names (``lever_arm_m``, ``lateral_m``,
        ``height_m``, ``roll_rad``, ``pitch_rad``, ``yaw_rad``; each optional, 0 if left
        out); InvalidInputError naming what is wrong."""
        if not isinstance(data, dict):
            raise InvalidInputError(f"a camera mounting must be a mapping, got {data!r}")
        if "T_vehicle_from_cam" in data:
            return cls.from_T_vehicle_from_cam(matrix_4x4(data["T_vehicle_from_cam"]))
        names = [f for f in cls.__dataclass_fields__ if f in data]
        unknown = sorted(set(data) - set(cls.__dataclass_fields__))
        if unknown:
            raise InvalidInputError(
                f"unknown mounting field(s) {unknown}: give T_vehicle_from_cam or "
                f"{', '.join(cls.__dataclass_fields__)}"
            )
        try:
            return cls(**{f: float(data[f]) for f in names})
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"mounting fields must be numbers ({exc})") from exc

    def to_dict(self) -> dict[str, float]:
        return {f: float(getattr(self, f)) for f in self.__dataclass_fields__}


def matrix_4x4(value) -> np.ndarray:
    """A 4x4 matrix from rows, 16 row-major values or ROS's ``{rows, cols, data}``."""
    if isinstance(value, dict):
        value = value.get("data")
    try:
        M = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"T_vehicle_from_cam must be numbers ({exc})") from exc
    if M.size != 16:
        raise InvalidInputError(f"T_vehicle_from_cam must hold 16 values, got {M.size}")
    return M.reshape(4, 4)

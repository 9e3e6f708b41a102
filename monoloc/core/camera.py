"""Pinhole camera intrinsics shared by the sim, the server and the vehicle."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from monoloc.core.errors import InvalidInputError


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels; pixel (0, 0) is the centre of the top-left pixel."""

    fx: float
    fy: float
    cx: float
    cy: float
    width_px: int
    height_px: int

    def __post_init__(self) -> None:
        values = (self.fx, self.fy, self.cx, self.cy)
        if not all(math.isfinite(v) for v in values) or self.fx <= 0 or self.fy <= 0:
            raise InvalidInputError(f"invalid camera intrinsics {values}")
        if self.width_px <= 0 or self.height_px <= 0:
            raise InvalidInputError(
                f"invalid image size {self.width_px}x{self.height_px} in camera intrinsics"
            )

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def horizontal_fov_rad(self) -> float:
        """Full horizontal field of view."""
        left = math.atan2(self.cx + 0.5, self.fx)
        right = math.atan2(self.width_px - 0.5 - self.cx, self.fx)
        return left + right

    def scaled(self, factor: float) -> CameraIntrinsics:
        """Intrinsics of the same camera with the image resized by ``factor``."""
        return CameraIntrinsics(
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
            width_px=max(1, round(self.width_px * factor)),
            height_px=max(1, round(self.height_px * factor)),
        )


# KITTI odometry camera 0 (grayscale, left), sequences 00-02.
KITTI_CAM0 = CameraIntrinsics(
    fx=718.856, fy=718.856, cx=607.1928, cy=185.2157, width_px=1241, height_px=376
)

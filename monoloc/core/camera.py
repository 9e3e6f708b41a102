"""Camera intrinsics shared by the sim, the server and the vehicle: a pinhole model and,
optionally, its lens distortion (OpenCV's and ROS CameraInfo's models)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from monoloc.core.errors import InvalidInputError

# distortion model -> the number of coefficients it takes, in ROS CameraInfo's D order
# (plumb_bob: k1 k2 p1 p2 [k3]; rational_polynomial: k1 k2 p1 p2 k3 k4 k5 k6, OpenCV's
# order too; equidistant, OpenCV's fisheye model: k1 k2 k3 k4)
DISTORTION_MODELS: dict[str, tuple[int, ...]] = {
    "plumb_bob": (4, 5),
    "rational_polynomial": (8,),
    "equidistant": (4,),
}
# names other tools give the same models
DISTORTION_ALIASES = {"radtan": "plumb_bob", "opencv": "plumb_bob", "fisheye": "equidistant"}


@dataclass(frozen=True)
class LensDistortion:
    """A lens distortion model (``DISTORTION_MODELS``) and its coefficients (D)."""

    model: str
    coefficients: tuple[float, ...]

    def __post_init__(self) -> None:
        model = DISTORTION_ALIASES.get(str(self.model).lower(), str(self.model).lower())
        if model not in DISTORTION_MODELS:
            raise InvalidInputError(
                f"unknown lens distortion model {self.model!r}: monoloc knows "
                f"{', '.join(DISTORTION_MODELS)} (pinhole: no distortion)"
            )
        coefficients = tuple(float(v) for v in self.coefficients)
        if len(coefficients) not in DISTORTION_MODELS[model]:
            raise InvalidInputError(
                f"{model} takes {' or '.join(map(str, DISTORTION_MODELS[model]))} "
                f"coefficients, got {len(coefficients)}"
            )
        if not all(math.isfinite(v) for v in coefficients):
            raise InvalidInputError(f"{model} coefficients must be finite, got {coefficients}")
        object.__setattr__(self, "model", model)
        object.__setattr__(self, "coefficients", coefficients)

    @property
    def is_zero(self) -> bool:
        return not any(self.coefficients)

    @classmethod
    def parse(cls, model: str | None, coefficients) -> LensDistortion | None:
        """From a CameraInfo-like pair; None for a pinhole camera ("none", "pinhole", an
        empty model, or all-zero coefficients)."""
        if model is None or str(model).lower() in ("", "none", "pinhole"):
            if coefficients is not None and any(float(v) for v in coefficients):
                raise InvalidInputError("distortion coefficients given without their model")
            return None
        distortion = cls(str(model), tuple(coefficients or ()))
        return None if distortion.is_zero else distortion


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels; pixel (0, 0) is the centre of the top-left pixel.
    ``distortion``: the lens's, None for an ideal pinhole (the server undistorts a
    query's keypoints with it, not its image)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width_px: int
    height_px: int
    distortion: LensDistortion | None = None

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

    @property
    def pinhole(self) -> CameraIntrinsics:
        """The same camera without its distortion (what undistorted pixels obey)."""
        return dataclasses.replace(self, distortion=None)

    def scaled(self, factor: float) -> CameraIntrinsics:
        """Intrinsics of the same camera with the image resized by ``factor``."""
        return CameraIntrinsics(
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
            width_px=max(1, round(self.width_px * factor)),
            height_px=max(1, round(self.height_px * factor)),
            distortion=self.distortion,  # coefficients act on normalised coordinates
        )


# KITTI odometry camera 0 (grayscale, left), sequences 00-02.
KITTI_CAM0 = CameraIntrinsics(
    fx=718.856, fy=718.856, cx=607.1928, cy=185.2157, width_px=1241, height_px=376
)

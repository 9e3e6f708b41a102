"""A camera with lens distortion, rendered exactly: the scene is drawn for a pinhole
"canvas" with the same focal length and a field of view wide enough for every ray the
lens sees, then each distorted pixel takes the canvas's value where its ray lands
(``cv2.remap``). The source of distorted pixel p is the ideal pinhole pixel of p under
the lens model (``cv2.undistortPoints`` / ``cv2.fisheye.undistortPoints``, iterated to
1e-6 px), so a 3D point the pinhole camera sees at q appears at ``distort(q)``: where
OpenCV's own ``projectPoints`` puts it with the same K and D.

Models: ``monoloc.core.camera.LensDistortion`` (plumb_bob, rational_polynomial,
equidistant), in ROS CameraInfo's D order, which is OpenCV's.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError

# the canvas's border beyond the outermost source pixel (bilinear reads one neighbour)
CANVAS_MARGIN_PX = 2
# a canvas larger than this many times the image's area means a lens whose rays leave
# any pinhole's field of view (or a wrong model): refused rather than rendered
MAX_CANVAS_AREA_RATIO = 9.0
# a source pixel must map back onto its distorted pixel this closely
INVERSE_TOLERANCE_PX = 1e-3


def _K_D(camera: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    return camera.K, np.asarray(camera.distortion.coefficients, dtype=np.float64)


def undistort_points(pixels_px: np.ndarray, camera: CameraIntrinsics) -> np.ndarray:
    """(N, 2) float64 ideal pinhole pixels (the same K) of distorted pixels (N, 2)."""
    pixels = np.asarray(pixels_px, dtype=np.float64).reshape(-1, 1, 2)
    if camera.distortion is None or not len(pixels):
        return pixels.reshape(-1, 2)
    import cv2

    K, D = _K_D(camera)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    if camera.distortion.model == "equidistant":
        ideal = cv2.fisheye.undistortPoints(pixels, K, D, R=None, P=K, criteria=criteria)
    else:
        ideal = cv2.undistortPoints(pixels, K, D, R=None, P=K, criteria=criteria)
    return ideal.reshape(-1, 2)


def distort_points(pixels_px: np.ndarray, camera: CameraIntrinsics) -> np.ndarray:
    """(N, 2) float64: where ideal pinhole pixels (N, 2) land through the lens."""
    pixels = np.asarray(pixels_px, dtype=np.float64).reshape(-1, 2)
    if camera.distortion is None or not len(pixels):
        return pixels
    import cv2

    K, D = _K_D(camera)
    rays = np.c_[(pixels - K[:2, 2]) / [K[0, 0], K[1, 1]], np.ones(len(pixels))]
    zero = np.zeros(3)
    if camera.distortion.model == "equidistant":
        seen = cv2.fisheye.projectPoints(rays.reshape(-1, 1, 3), zero, zero, K, D)[0]
    else:
        seen = cv2.projectPoints(rays, zero, zero, K, D)[0]
    return seen.reshape(-1, 2)


def project_points(points_cam: np.ndarray, camera: CameraIntrinsics) -> np.ndarray:
    """(N, 2) pixels of camera-frame points (N, 3) (z > 0) through the lens."""
    points = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    pinhole = points[:, :2] / points[:, 2:] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    return distort_points(pinhole, camera)


@dataclass(frozen=True)
class LensRemap:
    """How to draw a distorted camera: ``canvas`` the pinhole camera (same fx, fy; wider)
    the scene is rendered for; ``map_x_px``, ``map_y_px`` (H, W) float32 the canvas pixel
    each pixel of the distorted image shows (``cv2.remap``'s maps)."""

    camera: CameraIntrinsics
    canvas: CameraIntrinsics
    map_x_px: np.ndarray
    map_y_px: np.ndarray

    def apply(self, canvas_image: np.ndarray, nearest: bool = False) -> np.ndarray:
        """The distorted image (H, W) of a canvas image (canvas H, W); ``nearest`` for
        values that must not be blended (depth, ids)."""
        import cv2

        interpolation = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
        return cv2.remap(
            canvas_image, self.map_x_px, self.map_y_px, interpolation,
            borderMode=cv2.BORDER_REPLICATE,
        )  # fmt: skip


@functools.lru_cache(maxsize=8)
def lens_remap(camera: CameraIntrinsics) -> LensRemap:
    """The :class:`LensRemap` of a camera with lens distortion (cached per camera: a run
    computes it once)."""
    if camera.distortion is None:
        raise InvalidInputError("lens_remap needs a camera with lens distortion")
    w, h = camera.width_px, camera.height_px
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pixels = np.c_[u.ravel(), v.ravel()]
    source = undistort_points(pixels, camera)
    back = distort_points(source, camera) if np.isfinite(source).all() else None
    if back is None or np.abs(back - pixels).max() > INVERSE_TOLERANCE_PX:
        raise InvalidInputError(
            f"the {camera.distortion.model} lens {camera.distortion.coefficients} cannot be "
            f"inverted over the {w}x{h} image (a ray would fold back): not rendered"
        )
    x0 = math.floor(source[:, 0].min()) - CANVAS_MARGIN_PX
    y0 = math.floor(source[:, 1].min()) - CANVAS_MARGIN_PX
    x1 = math.ceil(source[:, 0].max()) + CANVAS_MARGIN_PX
    y1 = math.ceil(source[:, 1].max()) + CANVAS_MARGIN_PX
    width, height = x1 - x0 + 1, y1 - y0 + 1
    if width * height > MAX_CANVAS_AREA_RATIO * w * h:
        raise InvalidInputError(
            f"the {camera.distortion.model} lens {camera.distortion.coefficients} sees rays "
            f"a {width}x{height} pinhole canvas would be needed for: not rendered"
        )
    canvas = dataclasses.replace(
        camera.pinhole, cx=camera.cx - x0, cy=camera.cy - y0, width_px=width, height_px=height
    )
    map_x = (source[:, 0] - x0).reshape(h, w).astype(np.float32)
    map_y = (source[:, 1] - y0).reshape(h, w).astype(np.float32)
    return LensRemap(camera, canvas, map_x, map_y)

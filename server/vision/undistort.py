"""Lens distortion taken off a query's keypoints (docs/method.md section 6): the pixels a
pinhole camera with the same K would have seen, so PnP, matching by projection and the
pose covariances stay pinhole; the image itself is never remapped (a distorted query
costs what a pinhole one does)."""

from __future__ import annotations

import cv2
import numpy as np

from monoloc.core.camera import CameraIntrinsics


def undistort_pixels(pixels_px: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
    """(N, 2) float64 ideal pinhole pixels (same K) of distorted pixels (N, 2); the input
    as it is for a camera without distortion."""
    pixels = np.asarray(pixels_px, dtype=np.float64).reshape(-1, 2)
    distortion = intrinsics.distortion
    if distortion is None or not len(pixels):
        return pixels
    K = intrinsics.K
    D = np.asarray(distortion.coefficients, dtype=np.float64)
    points = pixels.reshape(-1, 1, 2)
    if distortion.model == "equidistant":
        ideal = cv2.fisheye.undistortPoints(points, K, D, P=K)
    else:  # plumb_bob, rational_polynomial: OpenCV's own coefficient order
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-6)
        ideal = cv2.undistortPoints(points, K, D, R=None, P=K, criteria=criteria)
    return ideal.reshape(-1, 2)


def distort_pixels(pixels_px: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
    """The inverse: where ideal pinhole pixels (N, 2) land through the lens (N, 2)."""
    pixels = np.asarray(pixels_px, dtype=np.float64).reshape(-1, 2)
    distortion = intrinsics.distortion
    if distortion is None or not len(pixels):
        return pixels
    K = intrinsics.K
    rays = np.c_[(pixels - K[:2, 2]) / [K[0, 0], K[1, 1]], np.ones(len(pixels))]
    D = np.asarray(distortion.coefficients, dtype=np.float64)
    zero = np.zeros(3)
    if distortion.model == "equidistant":
        out = cv2.fisheye.projectPoints(rays.reshape(-1, 1, 3), zero, zero, K, D)[0]
    else:
        out = cv2.projectPoints(rays, zero, zero, K, D)[0]
    return out.reshape(-1, 2)

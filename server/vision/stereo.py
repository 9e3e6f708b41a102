"""Keypoint depth from a rectified stereo pair (a fleet without LiDAR; docs/method.md s. 5).

The rule (monoloc's, documented here and in docs/notebook/map-building.md):

- Disparity: OpenCV's semi-global matching (``cv2.StereoSGBM``) of the left image against
  the right one, row by row (the pair is rectified: the same camera matrix, the right
  camera ``baseline_m`` along the left one's +x, as KITTI's P0 / P1). The search range
  covers depths down to ``min_depth_m``. Two checks inside SGBM keep only trustworthy
  pixels: the left-right consistency check (the right image's own best match must come
  back within ``lr_max_diff_px``) and the uniqueness ratio (the best cost must beat the
  second best by ``uniqueness_ratio`` %); small islands of disparity unlike their
  surroundings (speckles) are removed too.
- A keypoint takes a depth only if at least ``min_pixels`` pixels of the disc of radius
  ``window_radius_px`` around it have a disparity and their depths agree within
  ``max_relative_spread`` (the same consistency rule as the LiDAR's, so a keypoint on a
  depth edge gets none), and the depth (median) lies in [min_depth_m, max_depth_m]:
  beyond ``max_depth_m`` a disparity error of a quarter pixel is already metres of depth.
- The 3D point is the keypoint's own ray at that depth (it reprojects onto the keypoint).

Pure: images and numbers in, arrays out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.server.vision.depth import DepthAssociationConfig, backproject, depth_at_keypoints

SGBM_DISPARITY_SCALE = 16  # StereoSGBM returns fixed-point disparities * 16
SGBM_MODES = ("sgbm", "sgbm_3way", "hh")


@dataclass(frozen=True)
class StereoConfig:
    """Settings of SGBM and of the keypoint lookup (see the module docstring).

    min_depth_m sets the disparity search range (fx * baseline / min_depth_m, rounded up
    to a multiple of 16 and capped at ``max_disparities``); block_size_px is SGBM's
    matched block (odd); p1 / p2 are its smoothness penalties per block pixel; mode is
    OpenCV's ``sgbm`` (5 paths), ``sgbm_3way`` (faster, the default) or ``hh`` (8 paths,
    full image)."""

    min_depth_m: float = 2.5
    max_depth_m: float = 40.0
    block_size_px: int = 5
    p1_per_pixel: int = 8
    p2_per_pixel: int = 32
    uniqueness_ratio: int = 10
    lr_max_diff_px: int = 1
    speckle_window_px: int = 100
    speckle_range_px: int = 2
    max_disparities: int = 256
    window_radius_px: int = 1
    min_pixels: int = 4
    max_relative_spread: float = 0.05
    mode: str = "sgbm_3way"

    def __post_init__(self) -> None:
        if self.mode not in SGBM_MODES:
            raise InvalidInputError(f"unknown SGBM mode {self.mode!r}: {', '.join(SGBM_MODES)}")
        if not 0 < self.min_depth_m < self.max_depth_m:
            raise InvalidInputError(
                f"stereo depths need 0 < min_depth_m < max_depth_m, got {self.min_depth_m}, "
                f"{self.max_depth_m}"
            )
        if self.block_size_px < 1 or self.block_size_px % 2 == 0:
            raise InvalidInputError(f"block_size_px must be odd, got {self.block_size_px}")
        if self.max_disparities < 16 or self.max_disparities % 16:
            raise InvalidInputError(
                f"max_disparities must be a multiple of 16, got {self.max_disparities}"
            )
        if self.lr_max_diff_px < 0 or self.window_radius_px < 0 or self.min_pixels < 1:
            raise InvalidInputError(f"invalid StereoConfig {self}")


def disparity_range(fx_px: float, baseline_m: float, config: StereoConfig) -> int:
    """SGBM's numDisparities: enough for depths down to ``min_depth_m``, a multiple of 16."""
    needed = fx_px * baseline_m / config.min_depth_m
    return int(min(config.max_disparities, max(16, 16 * math.ceil(needed / 16))))


def _check_pair(left_gray: np.ndarray, right_gray: np.ndarray, baseline_m: float) -> None:
    if left_gray.ndim != 2 or left_gray.dtype != np.uint8:
        raise InvalidInputError(
            f"stereo images must be (H, W) uint8, got {left_gray.dtype} {left_gray.shape}"
        )
    if right_gray.shape != left_gray.shape or right_gray.dtype != np.uint8:
        raise InvalidInputError(
            f"the right image is {right_gray.dtype} {right_gray.shape[::-1]}, the left "
            f"{left_gray.dtype} {left_gray.shape[::-1]}: a rectified pair has one size"
        )
    if not (math.isfinite(baseline_m) and baseline_m > 0):
        raise InvalidInputError(f"the stereo baseline must be > 0 m, got {baseline_m}")


def disparity_map(
    left_gray: np.ndarray,
    right_gray: np.ndarray,
    fx_px: float,
    baseline_m: float,
    config: StereoConfig = StereoConfig(),
) -> np.ndarray:
    """Left-image disparity (H, W) float32 in pixels of a rectified pair of (H, W) uint8
    images; 0 where SGBM found none or its consistency checks rejected the pixel."""
    import cv2

    _check_pair(left_gray, right_gray, baseline_m)
    n_disp = disparity_range(fx_px, baseline_m, config)
    if n_disp >= left_gray.shape[1]:
        raise InvalidInputError(
            f"images {left_gray.shape[1]} px wide cannot hold {n_disp} disparities; raise "
            "min_depth_m"
        )
    bs = config.block_size_px
    matcher = cv2.StereoSGBM.create(
        minDisparity=0,
        numDisparities=n_disp,
        blockSize=bs,
        P1=config.p1_per_pixel * bs * bs,
        P2=config.p2_per_pixel * bs * bs,
        disp12MaxDiff=config.lr_max_diff_px,
        uniquenessRatio=config.uniqueness_ratio,
        speckleWindowSize=config.speckle_window_px,
        speckleRange=config.speckle_range_px * SGBM_DISPARITY_SCALE,
        preFilterCap=63,
        mode={
            "sgbm": cv2.STEREO_SGBM_MODE_SGBM,
            "sgbm_3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
            "hh": cv2.STEREO_SGBM_MODE_HH,
        }[config.mode],
    )
    raw = matcher.compute(left_gray, right_gray)
    disparity = raw.astype(np.float32) / SGBM_DISPARITY_SCALE
    disparity[raw <= 0] = 0.0  # invalid pixels come back as (minDisparity - 1) * 16
    return disparity


def depth_from_disparity(disparity_px: np.ndarray, fx_px: float, baseline_m: float) -> np.ndarray:
    """Depth (H, W) float32 in metres, 0 where the disparity is 0 (none)."""
    with np.errstate(divide="ignore"):
        depth = np.where(disparity_px > 0, fx_px * baseline_m / disparity_px, 0.0)
    return depth.astype(np.float32)


def stereo_depth_at_keypoints(
    keypoints_px: np.ndarray,
    left_gray: np.ndarray,
    right_gray: np.ndarray,
    baseline_m: float,
    intrinsics: CameraIntrinsics,
    config: StereoConfig = StereoConfig(),
) -> np.ndarray:
    """Depth (N,) float32 of keypoints (N, 2) of the left image; NaN where none is taken."""
    if left_gray.shape != (intrinsics.height_px, intrinsics.width_px):
        raise InvalidInputError(
            f"the left image is {left_gray.shape[1]}x{left_gray.shape[0]}, the camera "
            f"{intrinsics.width_px}x{intrinsics.height_px}"
        )
    disparity = disparity_map(left_gray, right_gray, intrinsics.fx, baseline_m, config)
    depth_image = depth_from_disparity(disparity, intrinsics.fx, baseline_m)
    rule = DepthAssociationConfig(
        min_points=config.min_pixels,
        max_relative_spread=config.max_relative_spread,
        min_depth_m=config.min_depth_m,
        max_depth_m=config.max_depth_m,
    )
    return depth_at_keypoints(keypoints_px, depth_image, config.window_radius_px, rule)


def points_from_stereo(
    keypoints_px: np.ndarray,
    left_gray: np.ndarray,
    right_gray: np.ndarray,
    baseline_m: float,
    intrinsics: CameraIntrinsics,
    config: StereoConfig = StereoConfig(),
) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints (N, 2) of the left image -> (points_cam (N, 3) float32 in the left
    camera's frame, has_point (N,) bool)."""
    depth = stereo_depth_at_keypoints(
        keypoints_px, left_gray, right_gray, baseline_m, intrinsics, config
    )
    has = np.isfinite(depth)
    return backproject(keypoints_px, np.nan_to_num(depth), intrinsics), has

"""3D points for keypoints, from a LiDAR scan or a registered depth image (docs/method.md s. 5).

The rule (monoloc's, documented here and in docs/notebook/map-building.md):

- LiDAR: the scan is projected into the image with the calibration (points with camera
  depth >= ``min_depth_m``); where several land on one pixel the nearest is kept. A
  keypoint looks at the projected points within ``radius_px`` (KITTI's 64 rings are about
  5 px apart at 718 px focal length, so 5 px always reaches a ring). It takes a depth
  only if at least ``min_points`` points are there and they are depth-consistent
  (max / min <= 1 + ``max_relative_spread``): a window that straddles a depth
  discontinuity (an object edge, where a slightly misplaced LiDAR point would give the
  background's depth) is dropped rather than guessed. The depth is the median of the
  window's points, and the 3D point is the keypoint's own ray at that depth, so it
  reprojects exactly onto the keypoint.
- Depth image: the same consistency rule on the valid (non-zero) pixels of a
  (2 * radius + 1)^2 window around the keypoint.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError


@dataclass(frozen=True)
class DepthAssociationConfig:
    radius_px: int = 5
    min_points: int = 2
    max_relative_spread: float = 0.05
    min_depth_m: float = 0.5
    max_depth_m: float = 120.0
    depth_image_radius_px: int = 1


def backproject(keypoints_px: np.ndarray, depth_m: np.ndarray, intrinsics: CameraIntrinsics):
    """Camera-frame points (N, 3) float32 on the keypoints' rays at the given depths (N,)."""
    x = (keypoints_px[:, 0] - intrinsics.cx) / intrinsics.fx
    y = (keypoints_px[:, 1] - intrinsics.cy) / intrinsics.fy
    return np.stack([x * depth_m, y * depth_m, depth_m], axis=1).astype(np.float32)


def project_points(points_cam: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
    """Pixel coordinates (N, 2) of camera-frame points (N, 3) (z must be > 0)."""
    z = points_cam[:, 2]
    u = intrinsics.fx * points_cam[:, 0] / z + intrinsics.cx
    v = intrinsics.fy * points_cam[:, 1] / z + intrinsics.cy
    return np.stack([u, v], axis=1)


def lidar_depth_image(
    points_lidar: np.ndarray,
    T_cam_from_lidar: np.ndarray,
    intrinsics: CameraIntrinsics,
    config: DepthAssociationConfig,
) -> np.ndarray:
    """Sparse depth image (H, W) float32 from a scan (N, 3+): 0 where no point landed."""
    pts = np.asarray(points_lidar, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise InvalidInputError(f"LiDAR points must be (N, 3) or (N, 4), got {pts.shape}")
    points_cam = pts[:, :3] @ T_cam_from_lidar[:3, :3].T + T_cam_from_lidar[:3, 3]
    z = points_cam[:, 2]
    keep = (z >= config.min_depth_m) & (z <= config.max_depth_m)
    points_cam = points_cam[keep]
    uv = np.rint(project_points(points_cam, intrinsics)).astype(np.int64)
    w, h = intrinsics.width_px, intrinsics.height_px
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    uv, z = uv[inside], points_cam[inside, 2]
    flat = uv[:, 1] * w + uv[:, 0]
    # Nearest point per pixel: sort far to near so the last write (the nearest) wins.
    order = np.argsort(-z, kind="stable")
    depth = np.zeros(h * w, dtype=np.float32)
    depth[flat[order]] = z[order]
    return depth.reshape(h, w)


def depth_at_keypoints(
    keypoints_px: np.ndarray,
    depth_image_m: np.ndarray,
    radius_px: int,
    config: DepthAssociationConfig,
) -> np.ndarray:
    """Depth (N,) float32 per keypoint by the consistency rule; NaN where none is taken."""
    kp = np.asarray(keypoints_px, dtype=np.float64).reshape(-1, 2)
    h, w = depth_image_m.shape
    if len(kp) == 0:
        return np.zeros(0, dtype=np.float32)
    r = radius_px
    padded = np.pad(depth_image_m.astype(np.float32), r, constant_values=0.0)
    u = np.clip(np.rint(kp[:, 0]).astype(np.int64), 0, w - 1)
    v = np.clip(np.rint(kp[:, 1]).astype(np.int64), 0, h - 1)
    offsets = np.arange(-r, r + 1)
    rows = v[:, None, None] + r + offsets[None, :, None]
    cols = u[:, None, None] + r + offsets[None, None, :]
    windows = padded[rows, cols].reshape(len(kp), -1)  # (N, (2r+1)^2)
    # Within the radius (a disc, not the square).
    disc = (offsets[:, None] ** 2 + offsets[None, :] ** 2 <= r * r).reshape(-1)
    windows = np.where(disc[None, :], windows, 0.0)
    valid = windows > 0
    count = valid.sum(axis=1)
    with np.errstate(invalid="ignore", all="ignore"):
        filled = np.where(valid, windows, np.nan)
        d_min = np.nanmin(np.where(count[:, None] > 0, filled, 1.0), axis=1)
        d_max = np.nanmax(np.where(count[:, None] > 0, filled, 1.0), axis=1)
        median = np.nanmedian(np.where(count[:, None] > 0, filled, 1.0), axis=1)
    ok = (count >= config.min_points) & (d_max <= d_min * (1.0 + config.max_relative_spread))
    ok &= (median >= config.min_depth_m) & (median <= config.max_depth_m)
    return np.where(ok, median, np.nan).astype(np.float32)


def points_from_lidar(
    keypoints_px: np.ndarray,
    points_lidar: np.ndarray,
    T_cam_from_lidar: np.ndarray,
    intrinsics: CameraIntrinsics,
    config: DepthAssociationConfig = DepthAssociationConfig(),
) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints (N, 2) -> (points_cam (N, 3) float32, has_point (N,) bool)."""
    depth_image = lidar_depth_image(points_lidar, T_cam_from_lidar, intrinsics, config)
    depth = depth_at_keypoints(keypoints_px, depth_image, config.radius_px, config)
    has = np.isfinite(depth)
    return backproject(keypoints_px, np.nan_to_num(depth), intrinsics), has


def points_from_depth_image(
    keypoints_px: np.ndarray,
    depth_image: np.ndarray,
    depth_scale_per_m: float,
    intrinsics: CameraIntrinsics,
    config: DepthAssociationConfig = DepthAssociationConfig(),
) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints (N, 2) + registered depth image (raw units, 0 = invalid) -> points, mask.

    ``depth_scale_per_m`` is raw units per metre (TUM: 5000).
    """
    if depth_scale_per_m <= 0 or not np.isfinite(depth_scale_per_m):
        raise InvalidInputError(f"depth scale must be positive, got {depth_scale_per_m}")
    if depth_image.ndim != 2:
        raise InvalidInputError(f"depth image must be 2-D, got shape {depth_image.shape}")
    depth_m = depth_image.astype(np.float32) / np.float32(depth_scale_per_m)
    depth = depth_at_keypoints(keypoints_px, depth_m, config.depth_image_radius_px, config)
    has = np.isfinite(depth)
    return backproject(keypoints_px, np.nan_to_num(depth), intrinsics), has

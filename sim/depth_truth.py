"""The rendered depth as ground truth for depths a method measured at keypoints (stereo,
LiDAR association): the true depth at each keypoint's pixel, and whether the surface is
smooth around it, so errors on object edges and in foliage can be told apart."""

from __future__ import annotations

import numpy as np


def rendered_depth_at(
    keypoints_px: np.ndarray, depth_m: np.ndarray, radius_px: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """(depth (N,) m at each keypoint's nearest pixel, smooth (N,) bool): smooth when no
    depth in the (2r+1)^2 window around it differs by more than 10 % (not on an edge,
    not in a tree's leaves). ``depth_m`` (H, W), non-finite where nothing was hit."""
    h, w = depth_m.shape
    u = np.clip(np.rint(keypoints_px[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.rint(keypoints_px[:, 1]).astype(int), 0, h - 1)
    padded = np.pad(np.where(np.isfinite(depth_m), depth_m, 1e4), radius_px, mode="edge")
    offsets = range(-radius_px, radius_px + 1)
    window = np.stack(
        [padded[v + radius_px + dy, u + radius_px + dx] for dy in offsets for dx in offsets],
        axis=1,
    )
    return depth_m[v, u], window.max(axis=1) / window.min(axis=1) < 1.1

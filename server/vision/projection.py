"""Projection-guided matching: match a query against a reference's 3D points where a
pose says they should appear.

Global matching (``vision.matching``) compares every query descriptor with every
reference descriptor, and its ratio test rejects a match whenever the reference holds a
second descriptor almost as close anywhere in the image: repeated facades by day, and at
night most of the lamp-lit scene (measured by the former bench/pnp_scale.py,
docs/notebook). An entry's PnP pose then rests on a fraction of the points it sees.
Given a pose of the query relative to the reference, each reference point is projected
into the query image and only the query keypoints within ``radius_px`` of it compete, so
the ratio test compares it with the few descriptors nearby instead of the whole image
(the search tracking front ends such as ORB-SLAM run against their local map).

The localizer uses it to refine each entry's pose (``PoseConfig.refine``):
the entry's own RANSAC or guided pose chooses where to look, the entry's points found
there are refit (inlier selection and LM), so the pose still comes from that entry's
correspondences only. The pose only decides which keypoints compete: one that is off by
more than the radius finds few right matches, and a refit is kept only when it keeps
more inliers than the pose it started from.

Pure: arrays in, (K, 2) index pairs out, as ``vision.matching`` gives.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import invert_rigid
from monoloc.server.vision.pnp import PnpConfig, RelativePose, refit_checked

_NO_MATCHES = np.zeros((0, 2), dtype=np.int32)


@dataclass(frozen=True)
class ProjectionMatchConfig:
    """radius_px: search radius around a projected reference point (8 px: around a pose
    PnP found, a right match lies within a few pixels; per-entry poses on dev city 3 were
    as accurate with 4 or 16 px); max_hamming_bits and ratio: the match rule among the
    keypoints in that window (d1 <= max_hamming_bits, d1 < ratio * d2); min_depth_m:
    reference points closer to the query camera are not projected. The
    :class:`KeypointGrid` a search runs on must have the same radius."""

    radius_px: float = 8.0
    max_hamming_bits: int = 64
    ratio: float = 0.9
    min_depth_m: float = 0.5

    def __post_init__(self) -> None:
        if not (math.isfinite(self.radius_px) and self.radius_px >= 1.0):
            raise InvalidInputError(f"ProjectionMatchConfig.radius_px must be >= 1: {self}")
        if not 0 <= self.max_hamming_bits <= 256:
            raise InvalidInputError(
                f"ProjectionMatchConfig.max_hamming_bits must be in [0, 256]: {self}"
            )
        if not 0.0 < self.ratio <= 1.0:
            raise InvalidInputError(f"ProjectionMatchConfig.ratio must be in (0, 1]: {self}")
        if not self.min_depth_m > 0:
            raise InvalidInputError(f"ProjectionMatchConfig.min_depth_m must be > 0: {self}")


class KeypointGrid:
    """The query's keypoints bucketed in cells of the search radius (built once a frame,
    shared by every reference)."""

    def __init__(
        self,
        keypoints_px: np.ndarray,
        descriptors: np.ndarray,
        intrinsics: CameraIntrinsics,
        radius_px: float,
    ) -> None:
        keypoints = np.ascontiguousarray(keypoints_px, dtype=np.float64).reshape(-1, 2)
        if not (math.isfinite(radius_px) and radius_px >= 1.0):
            raise InvalidInputError(f"KeypointGrid needs a radius >= 1 px, got {radius_px}")
        if not np.isfinite(keypoints).all():
            raise InvalidInputError("keypoints contain NaN or infinite values")
        descriptors = np.ascontiguousarray(descriptors)
        if descriptors.dtype != np.uint8 or descriptors.shape != (len(keypoints), 32):
            raise InvalidInputError(
                f"{len(keypoints)} keypoints need (N, 32) uint8 descriptors, got "
                f"{descriptors.shape} {descriptors.dtype}"
            )
        self.keypoints_px = keypoints
        self.words = descriptors.view(np.uint64)
        self.radius_px = float(radius_px)
        self.intrinsics = intrinsics
        self.grid_width = int(math.ceil(intrinsics.width_px / radius_px)) + 1
        self.grid_height = int(math.ceil(intrinsics.height_px / radius_px)) + 1
        cx = np.clip(np.floor(keypoints[:, 0] / radius_px), 0, self.grid_width - 1)
        cy = np.clip(np.floor(keypoints[:, 1] / radius_px), 0, self.grid_height - 1)
        cells = (cy * self.grid_width + cx).astype(np.int64)
        self.members = np.argsort(cells, kind="stable").astype(np.int64)
        counts = np.bincount(cells, minlength=self.grid_width * self.grid_height)
        self.start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)


def match_by_projection(
    grid: KeypointGrid,
    ref_descriptors: np.ndarray,
    points_ref_cam: np.ndarray,
    T_query_from_ref: np.ndarray,
    config: ProjectionMatchConfig,
) -> np.ndarray:
    """(K, 2) int32 [query keypoint, reference point] matches of one reference whose
    points (M, 3) (its camera frame) and descriptors (M, 32) uint8 are projected with the
    predicted T_query_from_ref (4, 4); a query keypoint matched by several reference
    points keeps the closest descriptor (ties: none). In reference order."""
    from monoloc.server.vision._window_kernel import window_match

    ref_descriptors = np.ascontiguousarray(ref_descriptors)
    points = np.ascontiguousarray(points_ref_cam, dtype=np.float64).reshape(-1, 3)
    if ref_descriptors.dtype != np.uint8 or ref_descriptors.shape != (len(points), 32):
        raise InvalidInputError(
            f"{len(points)} reference points need (M, 32) uint8 descriptors, got "
            f"{ref_descriptors.shape} {ref_descriptors.dtype}"
        )
    if config.radius_px != grid.radius_px:
        raise InvalidInputError(
            f"a {config.radius_px} px search on a grid of {grid.radius_px} px cells"
        )
    if not len(ref_descriptors) or not len(grid.keypoints_px):
        return _NO_MATCHES
    T = np.asarray(T_query_from_ref, dtype=np.float64)
    camera = grid.intrinsics
    pairs = np.empty((len(points), 2), dtype=np.int32)
    k = window_match(
        points,
        np.ascontiguousarray(T[:3, :3]),
        np.ascontiguousarray(T[:3, 3]),
        camera.fx,
        camera.fy,
        camera.cx,
        camera.cy,
        float(camera.width_px),
        float(camera.height_px),
        config.min_depth_m,
        grid.keypoints_px,
        grid.start,
        grid.members,
        grid.grid_width,
        grid.grid_height,
        grid.radius_px,
        grid.words,
        ref_descriptors.view(np.uint64),
        config.max_hamming_bits,
        config.ratio,
        pairs,
    )
    return pairs[:k]


def refine_by_projection(
    grid: KeypointGrid,
    ref_descriptors: np.ndarray,
    points_ref_cam: np.ndarray,
    rel: RelativePose,
    pnp: PnpConfig,
    config: ProjectionMatchConfig,
) -> tuple[np.ndarray, RelativePose] | None:
    """An accepted entry pose ``rel`` refit on the entry's points (M, 3) matched by
    projection from it: (the (K, 2) matches, the refit pose), or None when the matches
    or the refit keep no more inliers than ``rel`` or the refit fails its checks."""
    T_query_from_ref = invert_rigid(rel.T_ref_from_query)
    points = np.ascontiguousarray(points_ref_cam, dtype=np.float64).reshape(-1, 3)  # once
    pairs = match_by_projection(grid, ref_descriptors, points, T_query_from_ref, config)
    if len(pairs) <= rel.n_inliers:
        return None
    # the matched points are finite: the kernel projected each to a pixel in the window
    refit = refit_checked(
        grid.keypoints_px[pairs[:, 0]],
        points[pairs[:, 1]],
        T_query_from_ref,
        grid.intrinsics,
        pnp,
        rel.method,
    )
    if not refit.accepted or refit.n_inliers <= rel.n_inliers:
        return None
    return pairs, refit

"""Compile (or load from numba's on-disk cache) the vision kernels before serving.

The first call of a numba kernel in a process compiles it (~1-2 s) or loads it from the
cache (~0.1 s); a server calls :func:`warm_up` at start so that no request pays that.
"""

from __future__ import annotations

import numpy as np

from monoloc.core.camera import KITTI_CAM0
from monoloc.server._png_kernel import unfilter_rows
from monoloc.server.vision.joint import EntryInliers, best_start
from monoloc.server.vision.matching import match_descriptors
from monoloc.server.vision.pnp import (
    PnpConfig,
    estimate_relative_pose,
    estimate_relative_pose_guided,
    refit_relative_pose,
    robust_refit,
)
from monoloc.server.vision.pose_covariance import planar_pose_covariance
from monoloc.server.vision.projection import (
    KeypointGrid,
    ProjectionMatchConfig,
    match_by_projection,
)
from monoloc.server.vision.vlad import compute_vlad


def warm_up() -> None:
    """Run the PNG unfiltering kernel, the VLAD kernels, the matching kernel, PnP
    (RANSAC's inlier scoring + LM, guided PnP's guess scoring), matching by projection, the
    joint pose's start and robust refit, and the pose covariance once on a small exact
    scene."""
    rng = np.random.default_rng(0)
    descriptors = rng.integers(0, 256, size=(4, 32), dtype=np.uint8)
    compute_vlad(descriptors, descriptors[:2].astype(np.float32))
    match_descriptors(descriptors, descriptors)
    camera = KITTI_CAM0
    points_cam = np.stack(
        [rng.uniform(-5, 5, 40), rng.uniform(-2, 2, 40), rng.uniform(8, 30, 40)], axis=1
    )
    pixels = points_cam[:, :2] / points_cam[:, 2:] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    estimate_relative_pose(pixels, points_cam, camera, PnpConfig(), rng)
    estimate_relative_pose_guided(pixels, points_cam, [np.eye(4)], camera, PnpConfig(), rng)
    point_descriptors = rng.integers(0, 256, size=(40, 32), dtype=np.uint8)
    grid = KeypointGrid(pixels, point_descriptors, camera, ProjectionMatchConfig().radius_px)
    match_by_projection(grid, point_descriptors, points_cam, np.eye(4), ProjectionMatchConfig())
    # the refit of a pose on its projection matches (refine_rounds)
    refit_relative_pose(pixels, points_cam, np.eye(4), camera, PnpConfig(), "ransac")
    # the joint pose: its start chosen by counting the union's inliers under each member's
    # pose, then the Cauchy refit (LM with weights)
    members = [EntryInliers(np.eye(4), pixels, points_cam)] * 2
    best_start(members, [np.eye(4), np.eye(4)], camera, PnpConfig())
    robust_refit(
        points_cam, pixels, np.ones(len(pixels), dtype=bool), np.eye(3), np.zeros(3), camera.K,
        PnpConfig(), np.ones(len(pixels)), 2.385, 1,
    )  # fmt: skip
    # each hypothesis's pose covariance (the localizer's default), weighted by keypoint scales
    planar_pose_covariance(np.eye(4), points_cam, camera, keypoint_scales=np.ones(len(pixels)))
    # a mono PNG's scanlines (encoded_image.png_gray8_pixels), every filter type
    filtered = np.zeros((5, 3), dtype=np.uint8)
    filtered[:, 0] = np.arange(5)
    unfilter_rows(filtered.ravel(), 5, 2, 1, np.empty((5, 2), dtype=np.uint8))

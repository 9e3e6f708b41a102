"""How well a PnP pose is pinned down by its own inliers: the Gauss-Newton covariance of
the camera pose, marginalised to the planar pose (X, Y, psi) the filter uses.

With independent pixel noise of 1 px on each inlier's projection, the pose's covariance
to first order is (J^T J)^-1, J (2M, 6) the Jacobian of the M projections with respect to
a small motion of the camera in the world: a translation of its centre along the world
axes (dX, dY, dZ) and a rotation about the world axes through that centre (roll-, pitch-
and yaw-like, d_theta). The planar block (dX, dY, d_theta_z) of the full inverse is the
marginal covariance: height, pitch and roll free, as PnP leaves them.

What it measures that the inlier count does not: where the inliers lie. Fifty inliers
on one parked car 14 m away pin the pose down far less than fifty spread over both
facades and the road; the count is the same, the spread differs by an order of magnitude.
Measured on dev sim cities (every per-entry hypothesis of a query run, error against the
map's own frame): Spearman correlation of the position error with this spread 0.55-0.71,
with 1 / sqrt(inliers) 0.23-0.51, with the mean reprojection error 0.15 or less; and at
1 px the spread is close to the error's own size (its quartiles 0.013-0.054 m against
the error's 0.012-0.128 m). Scaled by the real pixel noise (the inliers' spread, or a
calibrated factor) it is a per-hypothesis covariance.

Not every inlier is located as well: ORB finds a keypoint on one level of its pyramid,
and one found on level L (scale s = 1.2^L) is placed to within about s px of the
full-resolution image. Given the keypoints' scales, each point's rows are weighed by
1 / s^2 (J^T W J), so that pixel_std_px is the noise of a full-resolution keypoint.
Night frames take more of their matches from the coarse levels (35 % from levels 5-7
against 17 % by day on the held-out city, measured by the former bench/pnp_scale.py,
docs/notebook), which this puts into their covariance instead of leaving it to a larger
pixel noise fitted for all.
"""

from __future__ import annotations

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError

# Fewer than this many points (3 give a finite-ambiguity P3P; each gives 2 equations for 6
# unknowns) leave J^T J singular or nearly so: no covariance.
MIN_POINTS = 4
# Points closer than this to the camera plane (m) are left out: their Jacobian blows up.
MIN_DEPTH_M = 0.1


def planar_pose_covariance(
    T_world_from_cam: np.ndarray,
    points_world: np.ndarray,
    intrinsics: CameraIntrinsics,
    pixel_std_px: float = 1.0,
    keypoint_scales: np.ndarray | None = None,
) -> np.ndarray | None:
    """(3, 3) covariance of the planar pose (X m, Y m, psi rad) of a camera at
    ``T_world_from_cam`` (4, 4) located from ``points_world`` (M, 3) (its inliers' 3D
    points, in the world frame) with ``pixel_std_px`` of independent noise on each pixel
    coordinate of a keypoint found at full resolution; ``keypoint_scales`` (M,): the
    query keypoints' ORB pyramid scales (``Features.scales``), a keypoint of scale s
    located s times less precisely (None: all at full resolution). None when the points
    cannot determine the pose (fewer than ``MIN_POINTS`` in front of the camera, or
    J^T W J singular)."""
    T = np.asarray(T_world_from_cam, dtype=np.float64)
    points = np.asarray(points_world, dtype=np.float64)
    if T.shape != (4, 4) or points.ndim != 2 or points.shape[1] != 3:
        raise InvalidInputError(
            f"need T_world_from_cam (4, 4) and points_world (M, 3), got {T.shape}, {points.shape}"
        )
    if not pixel_std_px > 0:
        raise InvalidInputError(f"pixel_std_px must be > 0, got {pixel_std_px}")
    weights = np.empty(0)
    if keypoint_scales is not None:
        scales = np.asarray(keypoint_scales, dtype=np.float64).reshape(-1)
        if len(scales) != len(points) or not (np.isfinite(scales).all() and (scales > 0).all()):
            raise InvalidInputError(
                f"need {len(points)} positive finite keypoint scales, got shape {scales.shape}"
            )
        weights = 1.0 / (scales * scales)
    from monoloc.server.vision._covariance_kernel import planar_covariance

    planar = np.empty((3, 3))
    used = planar_covariance(
        np.ascontiguousarray(T[:3, :3]),
        np.ascontiguousarray(T[:3, 3]),
        np.ascontiguousarray(points),
        weights,
        float(intrinsics.fx),
        float(intrinsics.fy),
        MIN_DEPTH_M,
        planar,
    )
    if used < MIN_POINTS or not np.isfinite(planar).all():
        return None
    # J^T J positive definite (checked by its Cholesky) makes this marginal of its
    # inverse positive definite too
    planar = 0.5 * (planar + planar.T) * pixel_std_px**2
    return planar


def position_spread_m(covariance: np.ndarray | None) -> float:
    """sqrt(var X + var Y) of a planar covariance (3, 3): one figure for how well a
    hypothesis's position is pinned down (NaN for None)."""
    if covariance is None:
        return float("nan")
    return float(np.sqrt(covariance[0, 0] + covariance[1, 1]))

"""Compiled Gauss-Newton information of a camera pose (numba). Imported lazily by
monoloc.server.vision.pose_covariance.

For each point in front of the camera, the two rows of the Jacobian of its projection
with respect to (camera centre dX, dY, dZ; rotation about the world axes through the
centre) are [-g, g x d] for the pixel coordinate whose gradient with respect to the point
in the camera frame is a, with g = R a (a turned into world axes) and d the point minus
the camera centre (world axes); their outer products are summed into the (6, 6)
information. One pass, no (M, 2, 6) arrays.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def pose_information(R, centre, points_world, weights, fx, fy, min_depth_m, info):
    """Fill info (6, 6) with J^T W J for the camera R (3, 3) world_from_cam at ``centre``
    (3,), W the points' ``weights`` (M,) (the inverse variance of each pixel coordinate,
    1 / px^2; an empty array: all 1); returns the number of points used (those deeper
    than ``min_depth_m`` in front of the camera)."""
    weighted = weights.shape[0] > 0
    for i in range(6):
        for j in range(6):
            info[i, j] = 0.0
    row = np.empty(6)
    used = 0
    for k in range(points_world.shape[0]):
        dx = points_world[k, 0] - centre[0]
        dy = points_world[k, 1] - centre[1]
        dz = points_world[k, 2] - centre[2]
        # p = R^T d
        x = R[0, 0] * dx + R[1, 0] * dy + R[2, 0] * dz
        y = R[0, 1] * dx + R[1, 1] * dy + R[2, 1] * dz
        z = R[0, 2] * dx + R[1, 2] * dy + R[2, 2] * dz
        if z <= min_depth_m:
            continue
        used += 1
        w = weights[k] if weighted else 1.0
        for coordinate in range(2):
            if coordinate == 0:
                a0, a1, a2 = fx / z, 0.0, -fx * x / (z * z)
            else:
                a0, a1, a2 = 0.0, fy / z, -fy * y / (z * z)
            g0 = R[0, 0] * a0 + R[0, 1] * a1 + R[0, 2] * a2
            g1 = R[1, 0] * a0 + R[1, 1] * a1 + R[1, 2] * a2
            g2 = R[2, 0] * a0 + R[2, 1] * a1 + R[2, 2] * a2
            row[0], row[1], row[2] = -g0, -g1, -g2
            row[3] = g1 * dz - g2 * dy
            row[4] = g2 * dx - g0 * dz
            row[5] = g0 * dy - g1 * dx
            for i in range(6):
                ri = w * row[i]
                for j in range(i, 6):
                    info[i, j] += ri * row[j]
    for i in range(6):
        for j in range(i):
            info[i, j] = info[j, i]
    return used


_PLANAR = (0, 1, 5)


@njit(cache=True, nogil=True)
def planar_covariance(R_world_from_cam, centre, points_world, weights, fx, fy, min_depth_m, out):
    """Fill out (3, 3) with the (dX, dY, rotation about world z) block of (J^T W J)^-1
    (``weights`` as for :func:`pose_information`); returns the number of points used, or
    -1 when J^T W J is not positive definite."""
    info = np.empty((6, 6))
    used = pose_information(
        R_world_from_cam, centre, points_world, weights, fx, fy, min_depth_m, info
    )
    if used < 4:
        return used
    # Cholesky of J^T J (positive definite unless the points are degenerate)
    L = np.zeros((6, 6))
    for i in range(6):
        for j in range(i + 1):
            s = info[i, j]
            for m in range(j):
                s -= L[i, m] * L[j, m]
            if i == j:
                if s <= 1e-12 * max(info[i, i], 1e-300):
                    return -1
                L[i, i] = np.sqrt(s)
            else:
                L[i, j] = s / L[j, j]
    # columns of the inverse for the planar unknowns: solve L L^T x = e_k
    for a in range(3):
        col = _PLANAR[a]
        y = np.zeros(6)
        for i in range(6):
            s = 1.0 if i == col else 0.0
            for m in range(i):
                s -= L[i, m] * y[m]
            y[i] = s / L[i, i]
        x = np.zeros(6)
        for i in range(5, -1, -1):
            s = y[i]
            for m in range(i + 1, 6):
                s -= L[m, i] * x[m]
            x[i] = s / L[i, i]
        for b in range(3):
            out[b, a] = x[_PLANAR[b]]
    return used

"""Compiled PnP refinement and inlier scoring (numba). Imported lazily by monoloc.server.vision.pnp.

Poses here are (R_query_from_ref (3, 3), t_query_from_ref (3,)) float64: they take points
in the reference camera frame to the query camera frame. Pixels follow the OpenCV
pinhole model without distortion (fx, fy, cx, cy).

Why not ``cv2.solvePnPRefineLM``: it goes through the generic projectPoints with its full
Jacobian bookkeeping, a large share of the PnP time of a reference; these loops with an
analytic SE(3) Jacobian do the same steps in a small fraction of it (bench/vision.py).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def inlier_errors(points_ref, pixels, R, t, fx, fy, cx, cy, threshold_px, errors_px, inliers):
    """Fill errors_px (M,) with the reprojection error of each point (a 1e-9 m floor on
    depth) and inliers (M,) bool with whether it is within ``threshold_px`` and in front
    of the camera: one pass, no depth array and no element-wise passes after it."""
    for k in range(points_ref.shape[0]):
        X, Y, Z = points_ref[k, 0], points_ref[k, 1], points_ref[k, 2]
        x = R[0, 0] * X + R[0, 1] * Y + R[0, 2] * Z + t[0]
        y = R[1, 0] * X + R[1, 1] * Y + R[1, 2] * Z + t[1]
        z = R[2, 0] * X + R[2, 1] * Y + R[2, 2] * Z + t[2]
        in_front = z > 0.0
        z = max(z, 1e-9)
        du = fx * x / z + cx - pixels[k, 0]
        dv = fy * y / z + cy - pixels[k, 1]
        errors_px[k] = np.sqrt(du * du + dv * dv)
        inliers[k] = in_front and errors_px[k] <= threshold_px


@njit(cache=True, nogil=True)
def count_inliers(points_ref, pixels, R, t, fx, fy, cx, cy, threshold_px, counts):
    """Fill counts (G,) with the number of points within ``threshold_px`` of their pixel
    and in front of the camera under each of G poses R (G, 3, 3), t (G, 3): the test of
    ``inlier_errors``, same arithmetic, without storing the errors."""
    for g in range(R.shape[0]):
        n = 0
        for k in range(points_ref.shape[0]):
            X, Y, Z = points_ref[k, 0], points_ref[k, 1], points_ref[k, 2]
            x = R[g, 0, 0] * X + R[g, 0, 1] * Y + R[g, 0, 2] * Z + t[g, 0]
            y = R[g, 1, 0] * X + R[g, 1, 1] * Y + R[g, 1, 2] * Z + t[g, 1]
            z = R[g, 2, 0] * X + R[g, 2, 1] * Y + R[g, 2, 2] * Z + t[g, 2]
            if not z > 0.0:
                continue
            z = max(z, 1e-9)
            du = fx * x / z + cx - pixels[k, 0]
            dv = fy * y / z + cy - pixels[k, 1]
            if np.sqrt(du * du + dv * dv) <= threshold_px:
                n += 1
        counts[g] = n


@njit(inline="always")
def _normal_equations(points_ref, pixels, mask, weights, R, t, fx, fy, cx, cy, H, g):
    """Gauss-Newton normal equations H (6, 6), g (6,) for a left perturbation
    (rotation vector w, translation v) of the pose, over the masked points, each point's
    squared error weighted by ``weights`` (M,) (its inverse variance; an empty array: all
    1); returns the weighted squared reprojection error sum at the pose. The Jacobian's
    two rows are scalars (no array per call: this runs up to four times per LM step)."""
    unit = weights.shape[0] == 0
    H[:, :] = 0.0
    g[:] = 0.0
    cost = 0.0
    for k in range(points_ref.shape[0]):
        if not mask[k]:
            continue
        X, Y, Z = points_ref[k, 0], points_ref[k, 1], points_ref[k, 2]
        x = R[0, 0] * X + R[0, 1] * Y + R[0, 2] * Z + t[0]
        y = R[1, 0] * X + R[1, 1] * Y + R[1, 2] * Z + t[1]
        z = R[2, 0] * X + R[2, 1] * Y + R[2, 2] * Z + t[2]
        if z <= 1e-9:
            continue
        iz = 1.0 / z
        ru = fx * x * iz + cx - pixels[k, 0]
        rv = fy * y * iz + cy - pixels[k, 1]
        wk = 1.0 if unit else weights[k]
        cost += wk * (ru * ru + rv * rv)
        # d(u, v)/d(x, y, z), then d(x, y, z)/d(w, v) = [-[p]_x | I]
        a, b = fx * iz, -fx * x * iz * iz
        c, d = fy * iz, -fy * y * iz * iz
        u0, u1, u2, u3, u4, u5 = b * y, a * z - b * x, -a * y, a, 0.0, b
        v0, v1, v2, v3, v4, v5 = -c * z + d * y, -d * x, c * x, 0.0, c, d
        g[0] += wk * (u0 * ru + v0 * rv)
        g[1] += wk * (u1 * ru + v1 * rv)
        g[2] += wk * (u2 * ru + v2 * rv)
        g[3] += wk * (u3 * ru + v3 * rv)
        g[4] += wk * (u4 * ru + v4 * rv)
        g[5] += wk * (u5 * ru + v5 * rv)
        H[0, 0] += wk * (u0 * u0 + v0 * v0)
        H[0, 1] += wk * (u0 * u1 + v0 * v1)
        H[0, 2] += wk * (u0 * u2 + v0 * v2)
        H[0, 3] += wk * (u0 * u3 + v0 * v3)
        H[0, 4] += wk * (u0 * u4 + v0 * v4)
        H[0, 5] += wk * (u0 * u5 + v0 * v5)
        H[1, 1] += wk * (u1 * u1 + v1 * v1)
        H[1, 2] += wk * (u1 * u2 + v1 * v2)
        H[1, 3] += wk * (u1 * u3 + v1 * v3)
        H[1, 4] += wk * (u1 * u4 + v1 * v4)
        H[1, 5] += wk * (u1 * u5 + v1 * v5)
        H[2, 2] += wk * (u2 * u2 + v2 * v2)
        H[2, 3] += wk * (u2 * u3 + v2 * v3)
        H[2, 4] += wk * (u2 * u4 + v2 * v4)
        H[2, 5] += wk * (u2 * u5 + v2 * v5)
        H[3, 3] += wk * (u3 * u3 + v3 * v3)
        H[3, 4] += wk * (u3 * u4 + v3 * v4)
        H[3, 5] += wk * (u3 * u5 + v3 * v5)
        H[4, 4] += wk * (u4 * u4 + v4 * v4)
        H[4, 5] += wk * (u4 * u5 + v4 * v5)
        H[5, 5] += wk * (u5 * u5 + v5 * v5)
    for i in range(6):
        for j in range(i):
            H[i, j] = H[j, i]
    return cost


@njit(inline="always")
def _damped_step(H, g, damping, A, step):
    """step (6,) = -(H + damping * diag(max(H_ii, 1e-12)))^-1 g, by Gaussian elimination
    with partial pivoting on the augmented (6, 7) scratch A (LAPACK's gesv on a 6 x 6
    system costs more in its call than in its arithmetic). A singular system gives
    non-finite numbers, which the callers' finiteness checks catch."""
    for i in range(6):
        for j in range(6):
            A[i, j] = H[i, j]
        A[i, i] += damping * max(H[i, i], 1e-12)
        A[i, 6] = -g[i]
    for c in range(6):
        p = c
        for r in range(c + 1, 6):
            if abs(A[r, c]) > abs(A[p, c]):
                p = r
        if p != c:
            for j in range(c, 7):
                A[c, j], A[p, j] = A[p, j], A[c, j]
        inv = 1.0 / A[c, c]
        for r in range(c + 1, 6):
            f = A[r, c] * inv
            if f != 0.0:
                for j in range(c + 1, 7):
                    A[r, j] -= f * A[c, j]
    for i in range(5, -1, -1):
        s = A[i, 6]
        for j in range(i + 1, 6):
            s -= A[i, j] * step[j]
        step[i] = s / A[i, i]


@njit(inline="always")
def _left_update(step, R, t, R_out, t_out):
    """(R_out, t_out) = exp(step[:3]) applied on the left of (R, t), plus step[3:] on t:
    Rodrigues' formula in scalars ([w]_x^2 = w w^T - |w|^2 I)."""
    w0, w1, w2 = step[0], step[1], step[2]
    theta2 = w0 * w0 + w1 * w1 + w2 * w2
    theta = np.sqrt(theta2)
    if theta < 1e-12:
        A, B = 1.0, 0.0
    else:
        A = np.sin(theta) / theta
        B = (1.0 - np.cos(theta)) / theta2
    d00 = 1.0 + B * (w0 * w0 - theta2)
    d11 = 1.0 + B * (w1 * w1 - theta2)
    d22 = 1.0 + B * (w2 * w2 - theta2)
    d01, d10 = B * w0 * w1 - A * w2, B * w0 * w1 + A * w2
    d02, d20 = B * w0 * w2 + A * w1, B * w0 * w2 - A * w1
    d12, d21 = B * w1 * w2 - A * w0, B * w1 * w2 + A * w0
    for j in range(3):
        r0, r1, r2 = R[0, j], R[1, j], R[2, j]
        R_out[0, j] = d00 * r0 + d01 * r1 + d02 * r2
        R_out[1, j] = d10 * r0 + d11 * r1 + d12 * r2
        R_out[2, j] = d20 * r0 + d21 * r1 + d22 * r2
    t0, t1, t2 = t[0], t[1], t[2]
    t_out[0] = d00 * t0 + d01 * t1 + d02 * t2 + step[3]
    t_out[1] = d10 * t0 + d11 * t1 + d12 * t2 + step[4]
    t_out[2] = d20 * t0 + d21 * t1 + d22 * t2 + step[5]


@njit(cache=True, nogil=True)
def refine_lm(points_ref, pixels, mask, weights, R, t, fx, fy, cx, cy, iterations):
    """Levenberg-Marquardt on the masked points' reprojection error, each point's squared
    error weighted by ``weights`` (M,) (empty: all 1), starting at (R, t); at most
    ``iterations`` accepted steps (and as many rejected ones). Returns the refined (R, t)
    (new arrays) and the final weighted squared error sum."""
    H = np.empty((6, 6))
    g = np.empty(6)
    H_new = np.empty((6, 6))
    g_new = np.empty(6)
    A = np.empty((6, 7))
    step = np.empty(6)
    R_cur, t_cur = R.copy(), t.copy()
    R_new, t_new = np.empty((3, 3)), np.empty(3)
    cost = _normal_equations(points_ref, pixels, mask, weights, R_cur, t_cur, fx, fy, cx, cy, H, g)
    damping = 1e-4
    accepted = 0
    for _ in range(2 * iterations):
        _damped_step(H, g, damping, A, step)
        _left_update(step, R_cur, t_cur, R_new, t_new)
        cost_new = _normal_equations(
            points_ref, pixels, mask, weights, R_new, t_new, fx, fy, cx, cy, H_new, g_new
        )
        if cost_new < cost:
            R_cur, R_new = R_new, R_cur
            t_cur, t_new = t_new, t_cur
            cost = cost_new
            H, H_new = H_new, H
            g, g_new = g_new, g
            damping = max(damping * 0.1, 1e-10)
            accepted += 1
            if accepted >= iterations:
                break
        else:
            damping *= 10.0
    return R_cur, t_cur, cost


@njit(cache=True, nogil=True)
def refine_rounds(
    points_ref,
    pixels,
    candidates,
    R,
    t,
    fx,
    fy,
    cx,
    cy,
    threshold_px,
    rounds,
    iterations,
    errors_px,
    inliers,
):
    """``rounds`` times: the inliers of (R, t) (``inlier_errors``; only where
    ``candidates`` (M,) bool is set, an empty array: everywhere), then unweighted
    ``refine_lm`` on them; a last selection. One call instead of a Python loop over the
    kernels (the refit of every entry pose runs it). Fills errors_px and inliers (M,) with
    the last selection; returns (R, t, status): 0 done, 1 fewer than 6 inliers before an
    LM, 2 LM left the finite numbers (the selection then is the one before it)."""
    unit = np.empty(0)
    masked = candidates.shape[0] > 0
    inlier_errors(points_ref, pixels, R, t, fx, fy, cx, cy, threshold_px, errors_px, inliers)
    if masked:
        for k in range(inliers.shape[0]):
            inliers[k] = inliers[k] and candidates[k]
    for _ in range(rounds):
        n = 0
        for k in range(inliers.shape[0]):
            n += inliers[k]
        if n < 6:
            return R, t, 1
        R_new, t_new, _ = refine_lm(
            points_ref, pixels, inliers, unit, R, t, fx, fy, cx, cy, iterations
        )
        total = 0.0
        for i in range(3):
            total += t_new[i]
            for j in range(3):
                total += R_new[i, j]
        if not np.isfinite(total):
            return R, t, 2
        R, t = R_new, t_new
        inlier_errors(points_ref, pixels, R, t, fx, fy, cx, cy, threshold_px, errors_px, inliers)
        if masked:
            for k in range(inliers.shape[0]):
                inliers[k] = inliers[k] and candidates[k]
    return R, t, 0


@njit(cache=True, nogil=True)
def best_guess_inliers(
    points_ref,
    pixels,
    T_ref_from_query,
    fx,
    fy,
    cx,
    cy,
    threshold_px,
    min_count,
    errors_px,
    inliers,
):
    """Of G guesses T_ref_from_query (G, 4, 4), the one under which the most points are
    within ``threshold_px`` and in front of the camera (``count_inliers``' test; the first
    of equals). Returns (its index, its count); when the count reaches ``min_count``,
    errors_px and inliers (M,) are filled with its ``inlier_errors`` (one call where the
    guided PnP of every entry made three: the guesses inverted, counted, then the best
    one's selection)."""
    n_guesses = T_ref_from_query.shape[0]
    R = np.empty((n_guesses, 3, 3))
    t = np.empty((n_guesses, 3))
    for g in range(n_guesses):
        # R_query_from_ref = R_ref_from_query^T, t_query_from_ref = -R^T t_ref_from_query
        for i in range(3):
            for j in range(3):
                R[g, i, j] = T_ref_from_query[g, j, i]
        for i in range(3):
            t[g, i] = -(
                R[g, i, 0] * T_ref_from_query[g, 0, 3]
                + R[g, i, 1] * T_ref_from_query[g, 1, 3]
                + R[g, i, 2] * T_ref_from_query[g, 2, 3]
            )
    counts = np.empty(n_guesses, dtype=np.int64)
    count_inliers(points_ref, pixels, R, t, fx, fy, cx, cy, threshold_px, counts)
    best = 0
    for g in range(1, n_guesses):
        if counts[g] > counts[best]:
            best = g
    if n_guesses and counts[best] >= min_count:
        inlier_errors(
            points_ref, pixels, R[best], t[best], fx, fy, cx, cy, threshold_px, errors_px, inliers
        )
    return best, counts[best] if n_guesses else -1

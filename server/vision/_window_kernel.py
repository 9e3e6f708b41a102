"""Compiled kernel of projection-guided matching (numba). Imported lazily by
monoloc.server.vision.projection.

The query keypoints are bucketed in square cells of the search radius, sorted by cell;
each projected reference point then looks only at the 3 x 3 cells around it.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from monoloc.server.vision._bits import FAR as _FAR
from monoloc.server.vision._bits import popcount64 as _popcount64


@njit(cache=True, boundscheck=False, nogil=True)
def window_match(
    points_ref,
    R,
    t,
    fx,
    fy,
    cx,
    cy,
    width_px,
    height_px,
    min_depth_m,
    keypoints_px,
    cell_start,
    cell_members,
    grid_width,
    grid_height,
    radius_px,
    query_words,
    ref_words,
    max_bits,
    ratio,
    out_pairs,
):
    """Project each reference point (M, 3) with (R_query_from_ref (3, 3), t (3,)); a point
    at least ``min_depth_m`` in front that lands within ``radius_px`` of the image
    (width_px x height_px) is matched among the query keypoints within ``radius_px`` of
    its projection: the nearest descriptor i at Hamming d1 matches if d1 <= max_bits and
    d1 < ratio * d2 (d2: the second-nearest in the window, infinite with one candidate).
    keypoints_px (N, 2); the keypoints of cell c (cells of ``radius_px``, row-major over
    grid_width x grid_height) are cell_members[cell_start[c]:cell_start[c + 1]].
    query_words (N, 4), ref_words (M, 4) uint64. A query keypoint matched by several
    points keeps the one at the smallest distance (none when tied). Writes the
    [query, reference] rows to out_pairs (>= M, 2) in reference order; returns their
    count."""
    m = points_ref.shape[0]
    n = keypoints_px.shape[0]
    r2 = radius_px * radius_px
    best_of_query = np.full(n, _FAR, dtype=np.int32)
    ties_of_query = np.zeros(n, dtype=np.int32)
    found_query = np.empty(m, dtype=np.int32)
    found_d = np.empty(m, dtype=np.int32)
    k = 0
    for j in range(m):
        X, Y, Z = points_ref[j, 0], points_ref[j, 1], points_ref[j, 2]
        z = R[2, 0] * X + R[2, 1] * Y + R[2, 2] * Z + t[2]
        if not z >= min_depth_m:
            continue
        u = fx * (R[0, 0] * X + R[0, 1] * Y + R[0, 2] * Z + t[0]) / z + cx
        v = fy * (R[1, 0] * X + R[1, 1] * Y + R[1, 2] * Z + t[1]) / z + cy
        if not (-radius_px <= u <= width_px - 1 + radius_px):
            continue
        if not (-radius_px <= v <= height_px - 1 + radius_px):
            continue
        cxl, cyl = int(np.floor(u / radius_px)), int(np.floor(v / radius_px))
        b0, b1, b2, b3 = ref_words[j, 0], ref_words[j, 1], ref_words[j, 2], ref_words[j, 3]
        d1 = _FAR
        d2 = _FAR
        best = -1
        for gy in range(max(cyl - 1, 0), min(cyl + 2, grid_height)):
            for gx in range(max(cxl - 1, 0), min(cxl + 2, grid_width)):
                c = gy * grid_width + gx
                for s in range(cell_start[c], cell_start[c + 1]):
                    i = cell_members[s]
                    du = keypoints_px[i, 0] - u
                    dv = keypoints_px[i, 1] - v
                    if du * du + dv * dv > r2:
                        continue
                    d = np.int32(
                        _popcount64(query_words[i, 0] ^ b0)
                        + _popcount64(query_words[i, 1] ^ b1)
                        + _popcount64(query_words[i, 2] ^ b2)
                        + _popcount64(query_words[i, 3] ^ b3)
                    )
                    if d < d1:
                        d2 = d1
                        d1 = d
                        best = i
                    elif d < d2:
                        d2 = d
        if best < 0 or d1 > max_bits:
            continue
        if d2 < _FAR and not (d1 < ratio * d2):
            continue
        found_query[j] = best
        found_d[j] = d1
        if d1 < best_of_query[best]:
            best_of_query[best] = d1
            ties_of_query[best] = 1
        elif d1 == best_of_query[best]:
            ties_of_query[best] += 1
        out_pairs[k, 1] = j
        k += 1
    kept = 0
    for row in range(k):
        j = out_pairs[row, 1]
        i = found_query[j]
        if found_d[j] == best_of_query[i] and ties_of_query[i] == 1:
            out_pairs[kept, 0] = i
            out_pairs[kept, 1] = j
            kept += 1
    return kept

"""Compiled kernel of projection-guided matching (numba). Imported lazily by
monoloc.server.vision.projection.

The query keypoints are bucketed in square cells of the search radius, sorted by cell;
each projected reference point then looks only at the 3 x 3 cells around it.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from monoloc.server.vision._bits import popcount64 as _popcount64

_FAR = np.int32(1 << 20)


@njit(cache=True, boundscheck=False, nogil=True)
def window_match(
    projected_px,
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
    out_d,
):
    """For each reference point j with a finite projection ``projected_px[j]`` (M, 2):
    the query keypoints within ``radius_px`` of it compete; the nearest descriptor i at
    Hamming d1 matches if d1 <= max_bits and d1 < ratio * d2 (d2: the second-nearest in
    the window, infinite with one candidate). keypoints_px (N, 2); the keypoints of cell c
    (cells of ``radius_px``, row-major over grid_width x grid_height) are
    cell_members[cell_start[c]:cell_start[c + 1]]. query_words (N, 4), ref_words (M, 4)
    uint64. Writes [query, reference] rows and d1 to out_pairs (>= M, 2), out_d (>= M);
    returns their count, in reference order."""
    m = projected_px.shape[0]
    r2 = radius_px * radius_px
    k = 0
    for j in range(m):
        u, v = projected_px[j, 0], projected_px[j, 1]
        if not (np.isfinite(u) and np.isfinite(v)):
            continue
        cx, cy = int(np.floor(u / radius_px)), int(np.floor(v / radius_px))
        b0, b1, b2, b3 = ref_words[j, 0], ref_words[j, 1], ref_words[j, 2], ref_words[j, 3]
        d1 = _FAR
        d2 = _FAR
        best = -1
        for gy in range(max(cy - 1, 0), min(cy + 2, grid_height)):
            for gx in range(max(cx - 1, 0), min(cx + 2, grid_width)):
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
        out_pairs[k, 0] = best
        out_pairs[k, 1] = j
        out_d[k] = d1
        k += 1
    return k

"""Compiled inner loop of the LiDAR ray caster (numba). Imported lazily by monoloc.sim.lidar."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, fastmath=False)
def cast(
    origins,
    dirs,
    q_origin,
    q_u,
    q_v,
    q_n,
    q_su,
    q_sv,
    q_two_sided,
    col_lo,
    col_hi,
    a_offset,
    a_width,
    a_height,
    a_ppm,
    a_tex_off,
    a_atlas,
    min_range,
    max_range,
):
    """Nearest hit per ray. origins (A, 3), dirs (A, B, 3) world; quads as arrays; each
    quad is tested only for columns col_lo..col_hi (mod A). Returns ranges (A, B)
    float64 (inf: no hit) and the index of the hit quad in the inputs (A, B) int32."""
    n_cols, n_beams = dirs.shape[0], dirs.shape[1]
    best = np.full((n_cols, n_beams), np.inf)
    ids = np.full((n_cols, n_beams), -1, np.int32)
    for q in range(q_origin.shape[0]):
        nx, ny, nz = q_n[q, 0], q_n[q, 1], q_n[q, 2]
        px, py, pz = q_origin[q, 0], q_origin[q, 1], q_origin[q, 2]
        ux, uy, uz = q_u[q, 0], q_u[q, 1], q_u[q, 2]
        vx, vy, vz = q_v[q, 0], q_v[q, 1], q_v[q, 2]
        su, sv = q_su[q], q_sv[q]
        lo, hi = col_lo[q], col_hi[q]
        if hi - lo + 1 >= n_cols:
            lo, hi = 0, n_cols - 1
        for cc in range(lo, hi + 1):
            c = cc % n_cols
            ox, oy, oz = origins[c, 0], origins[c, 1], origins[c, 2]
            num = nx * (px - ox) + ny * (py - oy) + nz * (pz - oz)
            for b in range(n_beams):
                dx, dy, dz = dirs[c, b, 0], dirs[c, b, 1], dirs[c, b, 2]
                den = nx * dx + ny * dy + nz * dz
                if den >= 0.0 and not q_two_sided[q]:
                    continue  # back face
                if den == 0.0:
                    continue
                t = num / den
                if t < min_range or t > max_range or t >= best[c, b]:
                    continue
                hx = ox + t * dx - px
                hy = oy + t * dy - py
                hz = oz + t * dz - pz
                s = hx * ux + hy * uy + hz * uz
                if s < 0.0 or s > su:
                    continue
                r = hx * vx + hy * vy + hz * vz
                if r < 0.0 or r > sv:
                    continue
                if a_offset[q] >= 0:
                    ix = int(s * a_ppm[q] + a_tex_off[q, 0])
                    iy = int(r * a_ppm[q] + a_tex_off[q, 1])
                    if ix < 0 or iy < 0 or ix >= a_width[q] or iy >= a_height[q]:
                        continue
                    if a_atlas[a_offset[q] + iy * a_width[q] + ix] < 128:
                        continue
                best[c, b] = t
                ids[c, b] = q
    return best, ids

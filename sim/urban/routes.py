"""Routes through a street grid and the lane-centre paths a vehicle follows.

Traffic drives on the right. A route is a walk over intersections that never turns
back and prefers streets it has not driven yet, so it covers the district and passes
the same places again (loops). Its path is the centre of the right-hand lane with
circular arcs at the turns, resampled every ``step_m``.
"""

from __future__ import annotations

import math

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.sim.path import Path, resample
from monoloc.sim.urban.street_grid import StreetGrid


def plan_route(
    grid: StreetGrid,
    rng: np.random.Generator,
    max_length_m: float = 1e9,
    start: tuple[int, int] = (0, 0),
) -> list[tuple[int, int]]:
    """Intersections visited, starting at ``start`` and ending once every street segment
    was driven (or the route reaches ``max_length_m``), then one block more."""
    edges = {frozenset((a, b)) for a in _nodes(grid) for b in grid.neighbours(a)}
    visits = dict.fromkeys(edges, 0)
    route = [start]
    prev = None
    length = 0.0
    extra = 2
    while True:
        here = route[-1]
        options = [n for n in grid.neighbours(here) if n != prev]
        counts = [visits[frozenset((here, n))] for n in options]
        fewest = min(counts)
        best = [n for n, c in zip(options, counts, strict=True) if c == fewest]
        nxt = best[int(rng.integers(len(best)))]
        visits[frozenset((here, nxt))] += 1
        length += float(np.linalg.norm(grid.node_xy(nxt) - grid.node_xy(here)))
        prev = here
        route.append(nxt)
        if min(visits.values()) > 0 or length >= max_length_m:
            extra -= 1
            if extra <= 0:
                return route


def _nodes(grid: StreetGrid):
    return [(i, j) for i in range(len(grid.xs)) for j in range(len(grid.ys))]


def lane_path(
    grid: StreetGrid,
    route: list[tuple[int, int]],
    lane_offset_m: float = 1.75,
    right_turn_radius_m: float = 6.0,
    left_turn_radius_m: float = 10.0,
    step_m: float = 0.25,
) -> Path:
    """Centre of the right-hand lane along ``route``, with arcs at turns."""
    if len(route) < 2:
        raise InvalidInputError(f"a route needs at least two intersections, got {route}")
    pts = [grid.node_xy(n) for n in route]
    dirs = [(b - a) / np.linalg.norm(b - a) for a, b in zip(pts[:-1], pts[1:], strict=True)]
    right = [np.array([d[1], -d[0]]) for d in dirs]
    pieces: list[np.ndarray] = [pts[0] + right[0] * lane_offset_m]
    for k in range(1, len(pts) - 1):
        d1, d2 = dirs[k - 1], dirs[k]
        corner = _intersect(
            pts[k] + right[k - 1] * lane_offset_m, d1, pts[k] + right[k] * lane_offset_m, d2
        )
        cross = d1[0] * d2[1] - d1[1] * d2[0]
        if corner is None or abs(cross) < 1e-9:
            pieces.append(pts[k] + right[k] * lane_offset_m)
            continue
        radius = left_turn_radius_m if cross > 0 else right_turn_radius_m
        theta = math.acos(float(np.clip(d1 @ d2, -1.0, 1.0)))
        tangent = radius * math.tan(theta / 2)
        t1 = corner - d1 * tangent
        side = np.array([-d1[1], d1[0]]) if cross > 0 else np.array([d1[1], -d1[0]])
        centre = t1 + side * radius
        a0 = math.atan2(t1[1] - centre[1], t1[0] - centre[0])
        sweep = theta if cross > 0 else -theta
        n_arc = max(4, int(abs(sweep) * radius / step_m))
        angles = a0 + np.linspace(0.0, sweep, n_arc)
        arc = centre + radius * np.stack([np.cos(angles), np.sin(angles)], axis=1)
        pieces.append(arc)
    pieces.append(pts[-1] + right[-1] * lane_offset_m)
    poly = np.vstack([np.atleast_2d(p) for p in pieces])
    return resample(poly, step_m)


def _intersect(p1, d1, p2, d2):
    den = d1[0] * d2[1] - d1[1] * d2[0]
    if abs(den) < 1e-12:
        return None
    t = ((p2[0] - p1[0]) * d2[1] - (p2[1] - p1[1]) * d2[0]) / den
    return p1 + t * d1

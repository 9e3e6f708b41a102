"""Routes through a street grid and the lane-centre paths a vehicle follows.

Traffic drives on the right. A route is a walk over intersections that never turns
back and prefers streets it has not driven yet, so it covers the district and passes
the same places again (loops). Its path is the centre of the right-hand lane with
circular arcs at the turns, resampled every ``step_m``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.sim.city import StreetGrid


@dataclass(frozen=True)
class Path:
    """A planar path: xy (N, 2) metres, heading_rad (N,), curvature (N,) 1/m (left
    positive), s_m (N,) arclength."""

    xy: np.ndarray
    heading_rad: np.ndarray
    curvature: np.ndarray
    s_m: np.ndarray

    @property
    def length_m(self) -> float:
        return float(self.s_m[-1])


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


def resample(poly: np.ndarray, step_m: float) -> Path:
    """Resample a polyline (N, 2) at constant arclength; headings and curvature from
    finite differences."""
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])
    poly = poly[keep]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    s_new = np.arange(0.0, s[-1], step_m)
    xy = np.stack([np.interp(s_new, s, poly[:, 0]), np.interp(s_new, s, poly[:, 1])], axis=1)
    d = np.gradient(xy, axis=0)
    heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    curvature = np.gradient(heading) / step_m
    return Path(xy=xy, heading_rad=heading, curvature=curvature, s_m=s_new)


def offset_path(path: Path, offset_m: np.ndarray, step_m: float = 0.25) -> Path:
    """``path`` shifted left by ``offset_m`` (N,) metres (negative: right)."""
    normal = np.stack([-np.sin(path.heading_rad), np.cos(path.heading_rad)], axis=1)
    return resample(path.xy + normal * offset_m[:, None], step_m)


def wandering_offset(
    path: Path,
    rng: np.random.Generator,
    max_offset_m: float = 1.5,
    max_heading_rad: float = math.radians(5.0),
) -> np.ndarray:
    """(N,) smooth lateral offsets within +-max_offset_m whose slope stays within
    +-max_heading_rad: a driver who does not keep to the lane centre."""
    s = path.s_m
    offset = np.zeros_like(s)
    for _ in range(4):
        wavelength = rng.uniform(60.0, 250.0)
        offset += rng.uniform(0.3, 1.0) * np.sin(
            2 * np.pi * s / wavelength + rng.uniform(0, 2 * np.pi)
        )
    offset += rng.uniform(-0.5, 0.5)
    offset *= max_offset_m / max(np.max(np.abs(offset)), 1e-9)
    slope = np.max(np.abs(np.gradient(offset, s))) if len(s) > 1 else 0.0
    if slope > max_heading_rad * 0.8:
        offset *= max_heading_rad * 0.8 / slope
    return offset

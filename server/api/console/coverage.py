"""Coverage gaps of a map: stretches of the mapped route with no (selected) entry nearby.

The route is each run's entries in time order (their planar positions joined by straight
segments). It is sampled every ``step_m``; a sample is uncovered when no entry of the
selection (for example the night entries) lies within ``radius_m`` of it, and runs of
uncovered samples are the gaps. Pure numpy + scipy: positions in, polylines out.

Bounds (what one request may cost, checked before sampling): the radius is at least
``MIN_RADIUS_M`` and the step at least ``MIN_STEP_M``; a selection whose routes need more
than ``MAX_SAMPLES`` samples is refused (:func:`sample_count`, no array built), and an
answer holds at most ``MAX_POINTS`` gap points (:func:`thin_gaps`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

MIN_RADIUS_M = 0.1
MIN_STEP_M = 0.025
MAX_SAMPLES = 2_000_000  # ~50 MB of float64 samples and distances
MAX_POINTS = 20_000  # gap points in one answer (~0.5 MB of JSON)


@dataclass(frozen=True)
class CoverageConfig:
    radius_m: float = 5.0
    step_m: float = 0.5

    @classmethod
    def for_radius(cls, radius_m: float) -> CoverageConfig:
        """A quarter of the radius, at most 1 m, at least ``MIN_STEP_M``."""
        return cls(radius_m=radius_m, step_m=max(min(radius_m / 4, 1.0), MIN_STEP_M))


@dataclass(frozen=True)
class Gap:
    """One uncovered stretch: its samples (M, 2) along the route and its length."""

    run_id: int | None
    points_xy_m: np.ndarray
    length_m: float


def sample_route(route_xy_m: np.ndarray, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``step_m`` along the polyline (N, 2), its vertices included, and the
    arc length (M,) of each."""
    route = np.asarray(route_xy_m, dtype=float).reshape(-1, 2)
    if len(route) < 2:
        return route.copy(), np.zeros(len(route))
    seg = np.diff(route, axis=0)
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    starts = np.concatenate([[0.0], np.cumsum(seg_len)])
    points, arcs = [], []
    for i, length in enumerate(seg_len):
        n = max(1, int(np.ceil(length / step_m)))
        f = np.arange(n) / n
        points.append(route[i] + f[:, None] * seg[i])
        arcs.append(starts[i] + f * length)
    points.append(route[-1:])
    arcs.append(starts[-1:])
    return np.concatenate(points), np.concatenate(arcs)


def sample_count(route_xy_m: np.ndarray, step_m: float) -> int:
    """How many points :func:`sample_route` would return, without building them."""
    route = np.asarray(route_xy_m, dtype=float).reshape(-1, 2)
    if len(route) < 2:
        return len(route)
    seg_len = np.hypot(*np.diff(route, axis=0).T)
    return int(np.maximum(1, np.ceil(seg_len / step_m)).sum()) + 1


def thin_gaps(gaps: list[Gap], max_points: int = MAX_POINTS) -> tuple[list[Gap], bool]:
    """The gaps with at most ``max_points`` points in all (every k-th sample of each,
    its ends kept; the longest gaps first if even their ends are too many), and whether
    anything was left out. Lengths are those of the whole gaps."""
    total = sum(len(g.points_xy_m) for g in gaps)
    if total <= max_points:
        return gaps, False
    if 2 * len(gaps) > max_points:
        gaps = sorted(gaps, key=lambda g: -g.length_m)[: max_points // 2]
    stride = max(1, int(np.ceil(total / max(1, max_points - 2 * len(gaps)))))
    thinned = []
    for gap in gaps:
        points = gap.points_xy_m
        keep = np.unique(np.concatenate([np.arange(0, len(points), stride), [len(points) - 1]]))
        thinned.append(Gap(gap.run_id, points[keep], gap.length_m))
    return thinned, True


def route_gaps(
    route_xy_m: np.ndarray,
    covered_xy_m: np.ndarray,
    config: CoverageConfig = CoverageConfig(),
    run_id: int | None = None,
) -> list[Gap]:
    """Stretches of one route (N, 2) farther than ``radius_m`` from every covered entry
    (K, 2); an empty selection leaves the whole route uncovered."""
    if not (config.radius_m >= MIN_RADIUS_M and config.step_m >= MIN_STEP_M):
        raise ValueError(f"radius_m must be >= {MIN_RADIUS_M}, step_m >= {MIN_STEP_M}")
    samples, arcs = sample_route(route_xy_m, config.step_m)
    if len(samples) == 0:
        return []
    covered = np.asarray(covered_xy_m, dtype=float).reshape(-1, 2)
    if len(covered):
        distance_m, _ = cKDTree(covered).query(samples, k=1)
        uncovered = distance_m > config.radius_m
    else:
        uncovered = np.ones(len(samples), dtype=bool)
    gaps = []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], uncovered.astype(np.int8), [0]])))
    for start, stop in zip(edges[::2], edges[1::2], strict=True):
        gaps.append(Gap(run_id, samples[start:stop], float(arcs[stop - 1] - arcs[start])))
    return gaps


def route_length_m(route_xy_m: np.ndarray) -> float:
    route = np.asarray(route_xy_m, dtype=float).reshape(-1, 2)
    return float(np.hypot(*np.diff(route, axis=0).T).sum()) if len(route) > 1 else 0.0

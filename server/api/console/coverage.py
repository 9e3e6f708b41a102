"""Coverage gaps of a map: stretches of the mapped route with no (selected) entry nearby.

The route is each run's entries in time order (their planar positions joined by straight
segments). It is sampled every ``step_m``; a sample is uncovered when no entry of the
selection (for example the night entries) lies within ``radius_m`` of it, and runs of
uncovered samples are the gaps. Pure numpy + scipy: positions in, polylines out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class CoverageConfig:
    radius_m: float = 5.0
    step_m: float = 0.5


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


def route_gaps(
    route_xy_m: np.ndarray,
    covered_xy_m: np.ndarray,
    config: CoverageConfig = CoverageConfig(),
    run_id: int | None = None,
) -> list[Gap]:
    """Stretches of one route (N, 2) farther than ``radius_m`` from every covered entry
    (K, 2); an empty selection leaves the whole route uncovered."""
    if config.radius_m <= 0 or config.step_m <= 0:
        raise ValueError("radius_m and step_m must be positive")
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

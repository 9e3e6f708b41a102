"""A district's street grid: where its streets run (z-up world, metres), how wide they
are, which have parking lanes; the walks of ``monoloc.sim.urban.routes`` and the blocks
of ``monoloc.sim.urban.district`` are laid on it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class StreetGrid:
    """A district's streets. Streets run along y at x = xs[i] and along x at y = ys[j];
    road_w_* are carriageway widths, side_w_* sidewalk widths, parking_* whether the
    street has parking lanes; node (i, j) is the intersection (xs[i], ys[j])."""

    name: str
    xs: np.ndarray
    ys: np.ndarray
    road_w_x: np.ndarray
    road_w_y: np.ndarray
    side_w_x: np.ndarray
    side_w_y: np.ndarray
    parking_x: np.ndarray
    parking_y: np.ndarray

    def node_xy(self, node: tuple[int, int]) -> np.ndarray:
        return np.array([self.xs[node[0]], self.ys[node[1]]])

    def neighbours(self, node: tuple[int, int]) -> list[tuple[int, int]]:
        i, j = node
        out = [(i + di, j + dj) for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1))]
        return [(a, b) for a, b in out if 0 <= a < len(self.xs) and 0 <= b < len(self.ys)]

    def road_width(self, a: tuple[int, int], b: tuple[int, int]) -> float:
        """Carriageway width of the street segment between adjacent nodes a and b."""
        return float(self.road_w_y[a[1]] if a[1] == b[1] else self.road_w_x[a[0]])

    def has_parking(self, a: tuple[int, int], b: tuple[int, int]) -> bool:
        return bool(self.parking_y[a[1]] if a[1] == b[1] else self.parking_x[a[0]])

    def bounds(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of the street centre lines."""
        return float(self.xs[0]), float(self.ys[0]), float(self.xs[-1]), float(self.ys[-1])


def make_grid(
    config,
    rng: np.random.Generator,
    name: str,
    blocks: tuple[int, int],
    origin_xy: tuple[float, float],
) -> StreetGrid:
    """Random street positions and widths for a district of ``blocks`` (bx, by), from
    the block lengths, lane widths and parking settings of ``config`` (a CityConfig)."""
    lane2 = 2 * config.lane_width_m
    arrays = {}
    for axis, n, o in (("x", blocks[0], origin_xy[0]), ("y", blocks[1], origin_xy[1])):
        lengths = rng.uniform(*config.block_length_m, size=n)
        parking = rng.random(n + 1) < config.parking_street_fraction
        road_w = lane2 + np.where(parking, 2 * config.parking_lane_width_m, 0.0)
        arrays[f"{axis}s"] = o + np.concatenate([[0.0], np.cumsum(lengths)])
        arrays[f"road_w_{axis}"] = road_w
        arrays[f"side_w_{axis}"] = rng.uniform(*config.sidewalk_width_m, size=n + 1)
        arrays[f"parking_{axis}"] = parking
    return StreetGrid(name=name, **arrays)

"""Planar paths a vehicle follows: a polyline resampled at constant arclength, with
headings and curvature, and a path shifted sideways (a driver off the centre line).

Frame: the z-up world's xy plane, metres; headings in radians from +x, counter-clockwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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
    max_offset_m: float,
    max_heading_rad: float,
    wavelength_m: tuple[float, float],
) -> np.ndarray:
    """(N,) smooth lateral offsets along ``path`` (a driver who does not keep to its
    centre): four sines of random wavelengths in ``wavelength_m`` (metres of arclength),
    scaled to reach +-max_offset_m, then flattened if needed so that their slope (the
    heading deviation from the path) stays within +-max_heading_rad."""
    s = path.s_m
    offset = np.zeros_like(s)
    for _ in range(4):
        wavelength = rng.uniform(*wavelength_m)
        offset += rng.uniform(0.3, 1.0) * np.sin(
            2 * np.pi * s / wavelength + rng.uniform(0, 2 * np.pi)
        )
    offset += rng.uniform(-0.5, 0.5)
    offset *= max_offset_m / max(np.max(np.abs(offset)), 1e-9)
    slope = np.max(np.abs(np.gradient(offset, s))) if len(s) > 1 else 0.0
    if slope > max_heading_rad:
        offset *= max_heading_rad / slope
    return offset

"""The indoor race track: a closed, smooth centre line on the floor of a room, and the
paths a 1:10 car drives on it (laps on the centre line, offset laps, lead-out).

A track is a distorted superellipse around the room's centre: a radius function of the
polar angle with a few random harmonics (bulges and dents, so corners differ), fitted
inside the room with a clearance from the walls and a minimum turning radius. It is
described by a small tuple of numbers (``TrackShape``), so that the floor texture can
redraw the exact same line from its ``TextureSpec``. Laps run counter-clockwise seen from
above (the infield is on the car's left), starting at the start line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.sim.path import Path, resample

_SAMPLES = 1440


@dataclass(frozen=True)
class TrackShape:
    """centre_xy (x, y) and semi_axes (a, b) in metres; exponent of the superellipse
    (2 = ellipse, larger = boxier); harmonics ((k, amplitude, phase_rad), ...) modulate
    the radius by (1 + sum amp * cos(k theta + phase)); start_theta_rad: polar angle of
    the start line."""

    centre_xy: tuple[float, float]
    semi_axes: tuple[float, float]
    exponent: float
    harmonics: tuple[tuple[int, float, float], ...]
    start_theta_rad: float

    def as_params(self) -> tuple:
        """Flat, hashable description (for a TextureSpec)."""
        return (
            *self.centre_xy,
            *self.semi_axes,
            self.exponent,
            self.start_theta_rad,
            *(v for h in self.harmonics for v in h),
        )

    @classmethod
    def from_params(cls, values: tuple) -> TrackShape:
        v = list(values)
        h = v[6:]
        harmonics = tuple((int(h[i]), h[i + 1], h[i + 2]) for i in range(0, len(h), 3))
        return cls((v[0], v[1]), (v[2], v[3]), v[4], harmonics, v[5])


def centre_line(shape: TrackShape, samples: int = _SAMPLES) -> np.ndarray:
    """(samples, 2) closed centre line (last point not repeated), counter-clockwise,
    starting at the start line."""
    theta = shape.start_theta_rad + np.linspace(0.0, 2 * np.pi, samples, endpoint=False)
    c, s = np.cos(theta), np.sin(theta)
    p = 2.0 / shape.exponent
    radius = np.ones_like(theta)
    for k, amp, phase in shape.harmonics:
        radius += amp * np.cos(k * theta + phase)
    x = shape.semi_axes[0] * np.sign(c) * np.abs(c) ** p * radius
    y = shape.semi_axes[1] * np.sign(s) * np.abs(s) ** p * radius
    return np.stack([x + shape.centre_xy[0], y + shape.centre_xy[1]], axis=1)


def curvature_closed(xy: np.ndarray) -> np.ndarray:
    """(N,) signed curvature of a closed polyline (central differences, wrapping)."""
    d1 = (np.roll(xy, -1, axis=0) - np.roll(xy, 1, axis=0)) / 2.0
    d2 = np.roll(xy, -1, axis=0) - 2 * xy + np.roll(xy, 1, axis=0)
    cross = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    return cross / np.maximum(np.linalg.norm(d1, axis=1) ** 3, 1e-12)


def make_track(
    room_size_m: tuple[float, float],
    rng: np.random.Generator,
    clearance_m: float = 1.1,
    min_turn_radius_m: float = 0.8,
    centre_xy: tuple[float, float] = (0.0, 0.0),
    twist: float = 1.0,
    attempts: int = 200,
) -> TrackShape:
    """A random track for a room of ``room_size_m`` (x, y) centred at ``centre_xy``:
    the centre line stays ``clearance_m`` from the walls and turns no tighter than
    ``min_turn_radius_m``. ``twist`` scales the harmonics (larger: twistier)."""
    half = np.array(room_size_m, dtype=np.float64) / 2.0 - clearance_m
    if np.any(half < 2 * min_turn_radius_m):
        raise InvalidInputError(
            f"room {room_size_m} too small for a track with {clearance_m} m clearance"
        )
    for attempt in range(attempts):
        damp = 1.0 - attempt / attempts  # relax towards a plain ellipse if nothing fits
        harmonics = tuple(
            (
                int(k),
                float(rng.uniform(0.03, 0.11) * twist * damp),
                float(rng.uniform(0, 2 * np.pi)),
            )
            for k in sorted(rng.choice([2, 3, 4, 5], size=int(rng.integers(2, 4)), replace=False))
        )
        shape = TrackShape(
            centre_xy,
            (1.0, 1.0),
            float(rng.uniform(2.2, 3.6) * damp + 2.0 * (1 - damp)),
            harmonics,
            0.0,
        )
        unit = centre_line(shape) - centre_xy
        extent = np.max(np.abs(unit), axis=0)
        shape = TrackShape(
            centre_xy, tuple(float(v) for v in half / extent), shape.exponent, harmonics, 0.0
        )
        xy = centre_line(shape)
        kappa = curvature_closed(xy)
        if np.max(np.abs(kappa)) <= 1.0 / min_turn_radius_m:
            # Start line on the straightest stretch.
            smooth = np.convolve(np.abs(np.tile(kappa, 3)), np.ones(60) / 60, "same")
            best = int(np.argmin(smooth[len(kappa) : 2 * len(kappa)]))
            start = float(2 * np.pi * best / len(kappa))
            return TrackShape(shape.centre_xy, shape.semi_axes, shape.exponent, harmonics, start)
    raise InvalidInputError(f"no track fits a room of {room_size_m} m")


def lap_path(shape: TrackShape, laps: float, step_m: float = 0.02) -> Path:
    """The centre line driven ``laps`` times from the start line (fractions allowed),
    resampled every ``step_m``."""
    loop = centre_line(shape)
    closed = np.vstack([loop, loop[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    lap_m = float(s[-1])
    total = laps * lap_m
    n_full = math.ceil(laps) + 1
    poly = np.vstack([loop] * n_full + [loop[:1]])
    path = resample(poly, step_m)
    keep = path.s_m <= total + 1e-9
    return Path(path.xy[keep], path.heading_rad[keep], path.curvature[keep], path.s_m[keep])


def lap_length_m(shape: TrackShape) -> float:
    loop = centre_line(shape)
    return float(np.sum(np.linalg.norm(np.diff(np.vstack([loop, loop[:1]]), axis=0), axis=1)))


def distance_to_line(points_xy: np.ndarray, line_xy: np.ndarray) -> np.ndarray:
    """(M,) distance of points (M, 2) to the nearest vertex of a dense polyline (N, 2)."""
    d = np.linalg.norm(points_xy[:, None, :] - line_xy[None, :, :], axis=2)
    return d.min(axis=1)


def inside_loop(points_xy: np.ndarray, loop_xy: np.ndarray) -> np.ndarray:
    """(M,) bool: points inside the closed polygon ``loop_xy`` (even-odd rule)."""
    x, y = points_xy[:, 0:1], points_xy[:, 1:2]
    xa, ya = loop_xy[:, 0][None], loop_xy[:, 1][None]
    xb, yb = np.roll(loop_xy[:, 0], -1)[None], np.roll(loop_xy[:, 1], -1)[None]
    crosses = ((ya > y) != (yb > y)) & (x < (xb - xa) * (y - ya) / (yb - ya + 1e-300) + xa)
    return np.sum(crosses, axis=1) % 2 == 1

"""The infield and the track side of an indoor room: tables with chairs and stacks of
boxes inside the loop, and movable obstacles (cardboard boxes, foam blocks) beside the
track whose arrangement changes between runs (``obstacles_scene``). Nothing stands on
the track: every object keeps a margin from the tape.
"""

from __future__ import annotations

import math

import numpy as np

from monoloc.sim.indoor.furniture import add_chair, add_textured_box, add_underside
from monoloc.sim.indoor.room import room_bounds
from monoloc.sim.indoor.track import centre_line, distance_to_line, inside_loop
from monoloc.sim.scene import KIND_CAR, Scene, SceneBuilder
from monoloc.sim.shapes import footprint_corners


def _free_spot(rng, config, loop, radius, inside, placed, margin=0.3, tries=200):
    """A random floor point at least ``margin`` + radius from the track edge, inside or
    outside the loop, not overlapping ``placed`` circles (x, y, r); None if none."""
    x0, y0, x1, y1 = room_bounds(config)
    for _ in range(tries):
        p = np.array(
            [
                rng.uniform(x0 + 0.2 + radius, x1 - 0.2 - radius),
                rng.uniform(y0 + 0.2 + radius, y1 - 0.2 - radius),
            ]
        )
        if inside_loop(p[None], loop)[0] != inside:
            continue
        if p[0] + radius > x1 - config.featureless_end_m:  # the bare end stays bare
            continue
        if distance_to_line(p[None], loop)[0] < config.track_width_m / 2 + margin + radius:
            continue
        if any(np.hypot(*(p - q[:2])) < radius + q[2] + 0.1 for q in placed):
            continue
        return p
    return None


def add_infield(b, rng, config, track) -> None:
    loop = centre_line(track, 720)
    placed: list[tuple[float, float, float]] = []
    for k in range(config.infield_objects):
        if k % 2 == 0:  # a table with legs and something on it
            length, width = rng.uniform(1.0, 1.4), rng.uniform(0.6, 0.8)
            radius = math.hypot(length, width) / 2 + 0.45  # with its chairs
            p = _free_spot(rng, config, loop, radius, True, placed)
            if p is None:
                continue
            yaw = rng.uniform(-np.pi, np.pi)
            top_z = rng.uniform(0.72, 0.76)
            add_textured_box(b, rng, p, yaw, length, width, top_z - 0.03, top_z, None, "wood")
            corners = footprint_corners(p, length, width, yaw)
            add_underside(b, rng, corners, top_z - 0.03, "wood")
            for c in corners:
                leg = p + (c - p) * 0.9
                add_textured_box(
                    b, rng, leg, yaw, 0.04, 0.04, 0.0, top_z - 0.03, None, "metal", top=False
                )
            add_textured_box(
                b,
                rng,
                p + rng.uniform(-0.2, 0.2, 2),
                yaw + rng.uniform(-0.3, 0.3),
                0.3,
                0.4,
                top_z,
                top_z + rng.uniform(0.15, 0.3),
                None,
                "cardboard",
            )
            placed.append((p[0], p[1], radius))
            fwd = np.array([math.cos(yaw), math.sin(yaw)])
            for side in (-1, 1):  # chairs at the long sides, pulled out a little
                if rng.random() < 0.7:
                    q = p + side * np.array([-fwd[1], fwd[0]]) * (
                        width / 2 + rng.uniform(0.05, 0.25)
                    )
                    q = q + fwd * rng.uniform(-length / 3, length / 3)
                    add_chair(b, rng, q, yaw + side * np.pi / 2 + np.pi + rng.normal(0, 0.3))
        else:  # a stack of cardboard boxes
            size = rng.uniform(0.35, 0.6)
            p = _free_spot(rng, config, loop, size * 0.75, True, placed)
            if p is None:
                continue
            z = 0.0
            for _ in range(int(rng.integers(1, 4))):
                h = rng.uniform(0.2, 0.4)
                add_textured_box(
                    b,
                    rng,
                    p + rng.normal(0, 0.03, 2),
                    rng.uniform(-np.pi, np.pi),
                    size,
                    size * rng.uniform(0.7, 1.0),
                    z,
                    z + h,
                    None,
                    "cardboard",
                )
                z += h
                size *= rng.uniform(0.75, 0.95)
            placed.append((p[0], p[1], 0.45))


def obstacle_slots(rng, config, track, walls) -> np.ndarray:
    """(N, 3) x, y, yaw of places beside the track (inside and outside the loop) where
    an obstacle may stand."""
    loop = centre_line(track, 720)
    slots: list[tuple[float, float, float]] = []
    for k in range(2 * config.obstacles):
        p = _free_spot(
            rng, config, loop, 0.3, k % 2 == 0, [(x, y, 0.3) for x, y, _ in slots], margin=0.12
        )
        if p is not None:
            slots.append((float(p[0]), float(p[1]), float(rng.uniform(-np.pi, np.pi))))
    return np.array(slots, dtype=np.float64).reshape(-1, 3)


def obstacles_scene(
    slots: np.ndarray, seed: int, variant: int, occupancy: float = 0.5, change_fraction: float = 0.4
) -> Scene:
    """Obstacles of one run: ``variant`` 0 is the reference arrangement; another variant
    re-draws each slot with probability ``change_fraction`` (moved, removed, new)."""
    n = len(slots)
    base = np.random.default_rng([seed, 2])
    occupied = base.random(n) < occupancy
    box_seed = base.integers(0, 2**31, size=n)
    shift = base.uniform(-0.1, 0.1, size=(n, 2))
    if variant:
        rng = np.random.default_rng([seed, 3, variant])
        change = rng.random(n) < change_fraction
        occupied = np.where(change, rng.random(n) < occupancy, occupied)
        box_seed = np.where(change, rng.integers(0, 2**31, size=n), box_seed)
        shift = np.where(change[:, None], rng.uniform(-0.15, 0.15, size=(n, 2)), shift)
    b = SceneBuilder()
    for k in np.flatnonzero(occupied):
        r = np.random.default_rng(int(box_seed[k]))
        x, y, yaw = slots[k]
        foam = r.random() < 0.3
        size = r.uniform(0.2, 0.35) if foam else r.uniform(0.25, 0.45)
        height = r.uniform(0.1, 0.2) if foam else r.uniform(0.2, 0.45)
        add_textured_box(
            b,
            r,
            (x + shift[k, 0], y + shift[k, 1]),
            yaw + r.uniform(-0.5, 0.5),
            size,
            size * r.uniform(0.7, 1.0),
            0.0,
            height,
            None,
            "foam" if foam else "cardboard",
            kind=KIND_CAR,
        )
    return b.build()

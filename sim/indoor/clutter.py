"""Near clutter: chairs, stands and people's legs right beside the taped track, part of
the room's static scene (see ``NearClutterConfig`` for why). World frame z up, metres.
"""

from __future__ import annotations

import math

import numpy as np

from monoloc.sim.indoor.furniture import add_chair, add_textured_box
from monoloc.sim.indoor.room import RoomConfig, room_bounds
from monoloc.sim.indoor.track import TrackShape, centre_line, distance_to_line
from monoloc.sim.scene import SceneBuilder

_KINDS = ("chair", "stand", "legs")
# The radius of each kind's footprint in any orientation, metres (its centre sits this
# far beyond its near edge): a turned chair's seat corner or back, a stand's foot, shoes.
_RADIUS_M = {"chair": 0.34, "stand": 0.18, "legs": 0.3}


def add_near_clutter(
    b: SceneBuilder, rng: np.random.Generator, config: RoomConfig, track: TrackShape
) -> int:
    """Add ``config.near_clutter.items`` objects beside the track; returns how many stand
    (none on the bare end)."""
    clutter = config.near_clutter
    if clutter.items <= 0:
        return 0
    loop = centre_line(track, 720)
    step = np.linalg.norm(np.diff(loop, axis=0, append=loop[:1]), axis=1)
    s_m = np.concatenate([[0.0], np.cumsum(step)[:-1]])
    length_m = float(step.sum())
    x_bare = room_bounds(config)[2] - config.featureless_end_m
    weights = np.asarray(clutter.kinds, dtype=np.float64)
    spacing = length_m / clutter.items
    placed = 0
    for k in range(clutter.items):
        s = (k + rng.uniform(0.2, 0.8)) * spacing
        i = int(np.searchsorted(s_m, s)) % len(loop)
        tangent = loop[(i + 1) % len(loop)] - loop[i - 1]
        tangent = tangent / np.linalg.norm(tangent)
        left = np.array([-tangent[1], tangent[0]])  # inside the counter-clockwise loop
        side = 1.0 if rng.random() < 0.5 else -1.0
        kind = str(rng.choice(_KINDS, p=weights / weights.sum()))
        gap = rng.uniform(*clutter.gap_m)
        reach = config.track_width_m / 2 + gap + _RADIUS_M[kind]
        p = loop[i] + side * left * reach
        if p[0] + _RADIUS_M[kind] > x_bare:  # the bare end stays bare
            continue
        if distance_to_line(p[None], loop)[0] < reach - 0.01:  # another part of the track
            continue
        yaw = math.atan2(tangent[1], tangent[0])
        if kind == "chair":
            add_chair(b, rng, p, yaw + rng.uniform(-math.pi, math.pi))
        elif kind == "stand":
            _stand(b, rng, p)
        else:
            _legs(b, rng, p, yaw + side * math.pi / 2 + math.pi + rng.normal(0.0, 0.4))
        placed += 1
    return placed


def _stand(b: SceneBuilder, rng, p: np.ndarray) -> None:
    """A light or microphone stand: a foot, a thin pole and a box (lamp, mic) on top."""
    top = rng.uniform(0.7, 1.3)
    add_textured_box(b, rng, p, rng.uniform(-np.pi, np.pi), 0.24, 0.24, 0.0, 0.03, None, "metal")
    add_textured_box(b, rng, p, 0.0, 0.025, 0.025, 0.03, top, None, "metal", top=False)
    add_textured_box(
        b, rng, p, rng.uniform(-np.pi, np.pi), 0.12, 0.16, top, top + 0.12, None,
        str(rng.choice(["metal", "foam", "cardboard"])),
    )  # fmt: skip


def _legs(b: SceneBuilder, rng, p: np.ndarray, facing_rad: float) -> None:
    """A person standing, seen from a 1:10 car: shoes and two trouser legs to the knee
    and above (0.75-0.9 m), 0.1-0.2 m apart."""
    forward = np.array([math.cos(facing_rad), math.sin(facing_rad)])
    across = np.array([-forward[1], forward[0]])
    apart = rng.uniform(0.1, 0.2)
    height = rng.uniform(0.75, 0.9)
    cloth = str(rng.choice(["foam", "cardboard", "wood"]))
    for side in (-0.5, 0.5):
        q = p + across * side * apart + forward * float(np.clip(rng.normal(0.0, 0.04), -0.05, 0.05))
        add_textured_box(b, rng, q + forward * 0.05, facing_rad, 0.27, 0.1, 0.0, 0.08, None, "foam")
        add_textured_box(b, rng, q, facing_rad, 0.12, 0.13, 0.08, height, None, cloth, top=False)

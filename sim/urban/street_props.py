"""Street furniture and parked cars: lamps, trees, signs along a sidewalk, and cars.

Every prop draws its shape and texture seeds from the generator it is given, in a fixed
order, so a seed reproduces the same street.
"""

from __future__ import annotations

import math

import numpy as np

from monoloc.sim.scene import (
    KIND_CAR,
    KIND_FOLIAGE,
    KIND_GLASS,
    KIND_LAMP,
    KIND_POLE,
    KIND_SIGN,
    SceneBuilder,
)
from monoloc.sim.shapes import add_billboard, add_box, footprint_corners, texture_size_px
from monoloc.sim.textures import TextureSpec, texture_seed


def add_street_furniture(b, rng, config, start, end, normal, z, walk_w):
    """Lamps, trees and signs on the sidewalk of width ``walk_w`` in front of the frontage
    line start->end (buildings lie along ``normal``, the kerb against it)."""
    length = float(np.linalg.norm(end - start))
    if length < 5.0:
        return
    d = (end - start) / length
    kerb_dist = walk_w - 0.5
    lamp_pos = rng.uniform(3.0, 12.0)
    while lamp_pos < length - 3.0:
        _lamp(b, rng, start + d * lamp_pos - normal * kerb_dist, -normal, z)
        lamp_pos += rng.uniform(*config.lamp_spacing_m)
    if walk_w > 3.0 and rng.random() < config.tree_street_fraction:
        t = rng.uniform(4.0, 8.0)
        while t < length - 3.0:
            _tree(b, rng, start + d * t - normal * (walk_w - 1.0), z)
            t += rng.uniform(7.0, 12.0)
    for t in (2.0, length - 2.0):
        if rng.random() < 0.35:
            _sign(b, rng, start + d * t - normal * kerb_dist, d if t < 2.5 else -d, z)


def _lamp(b, rng, p_xy, towards_road, z):
    pole_h = rng.uniform(6.0, 8.0)
    metal = TextureSpec("metal", 16, int(pole_h * 40), texture_seed(rng), (("ppm", 40.0),))
    corners = np.array(
        [
            [p_xy[0] - 0.08, p_xy[1] + 0.08],
            [p_xy[0] + 0.08, p_xy[1] + 0.08],
            [p_xy[0] + 0.08, p_xy[1] - 0.08],
            [p_xy[0] - 0.08, p_xy[1] - 0.08],
        ]
    )
    add_box(b, corners, z - 0.05, z + pole_h, [metal] * 4, 40.0, KIND_POLE, reflectance=0.5)
    head_xy = p_xy + towards_road * 1.3
    hc = np.array(
        [
            [head_xy[0] - 0.3, head_xy[1] + 0.15],
            [head_xy[0] + 0.3, head_xy[1] + 0.15],
            [head_xy[0] + 0.3, head_xy[1] - 0.15],
            [head_xy[0] - 0.3, head_xy[1] - 0.15],
        ]
    )
    lamp = TextureSpec("lamp", 24, 12, texture_seed(rng), (("ppm", 40.0),))
    add_box(
        b,
        hc,
        z + pole_h - 0.2,
        z + pole_h,
        [lamp] * 4,
        40.0,
        KIND_LAMP,
        top_spec=lamp,
        reflectance=0.6,
    )
    arm = np.array([p_xy, head_xy])
    mid = arm.mean(axis=0)
    ac = np.array(
        [
            [mid[0] - 0.65, mid[1] + 0.04],
            [mid[0] + 0.65, mid[1] + 0.04],
            [mid[0] + 0.65, mid[1] - 0.04],
            [mid[0] - 0.65, mid[1] - 0.04],
        ]
    )
    if abs(towards_road[1]) > abs(towards_road[0]):
        ac = np.array(
            [
                [mid[0] - 0.04, mid[1] + 0.65],
                [mid[0] + 0.04, mid[1] + 0.65],
                [mid[0] + 0.04, mid[1] - 0.65],
                [mid[0] - 0.04, mid[1] - 0.65],
            ]
        )
    add_box(b, ac, z + pole_h - 0.1, z + pole_h, [metal] * 4, 40.0, KIND_POLE)
    b.add_light(
        (head_xy[0], head_xy[1], z + pole_h - 0.3), 1.0, (towards_road[0], towards_road[1], 0.0)
    )


def _tree(b, rng, p_xy, z):
    trunk_h = rng.uniform(2.2, 3.2)
    bark = TextureSpec(
        "metal", 20, int(trunk_h * 40), texture_seed(rng), (("ppm", 40.0), ("bark", True))
    )
    r = rng.uniform(0.1, 0.16)
    corners = np.array(
        [
            [p_xy[0] - r, p_xy[1] + r],
            [p_xy[0] + r, p_xy[1] + r],
            [p_xy[0] + r, p_xy[1] - r],
            [p_xy[0] - r, p_xy[1] - r],
        ]
    )
    add_box(b, corners, z - 0.05, z + trunk_h + 0.5, [bark] * 4, 40.0, KIND_POLE, reflectance=0.3)
    size = rng.uniform(3.0, 5.0)
    yaw = rng.uniform(0, np.pi)
    for k in range(2):
        spec = TextureSpec(
            "foliage", int(size * 30), int(size * 30), texture_seed(rng), (("ppm", 30.0),)
        )
        add_billboard(
            b,
            (p_xy[0], p_xy[1], z + trunk_h + size / 2 - 0.3),
            yaw + k * np.pi / 2,
            size,
            size,
            spec,
            30.0,
            KIND_FOLIAGE,
            reflectance=0.2,
        )


def _sign(b, rng, p_xy, facing, z):
    post = TextureSpec("metal", 8, 100, texture_seed(rng), (("ppm", 40.0),))
    corners = np.array(
        [
            [p_xy[0] - 0.03, p_xy[1] + 0.03],
            [p_xy[0] + 0.03, p_xy[1] + 0.03],
            [p_xy[0] + 0.03, p_xy[1] - 0.03],
            [p_xy[0] - 0.03, p_xy[1] - 0.03],
        ]
    )
    add_box(b, corners, z - 0.05, z + 2.5, [post] * 4, 40.0, KIND_POLE, reflectance=0.5)
    spec = TextureSpec("sign", 60, 60, texture_seed(rng), (("ppm", 100.0),))
    yaw = math.atan2(facing[1], facing[0])
    add_billboard(
        b, (p_xy[0], p_xy[1], z + 2.4), yaw, 0.6, 0.6, spec, 100.0, KIND_SIGN, reflectance=0.9
    )


def add_car(b: SceneBuilder, xy, yaw: float, seed: int) -> None:
    """A parked car (two textured boxes: body and cabin) centred at ``xy``."""
    rng = np.random.default_rng(seed)
    ppm = 50.0
    length, width = rng.uniform(3.9, 4.8), rng.uniform(1.7, 1.85)
    tone = float(rng.choice([rng.uniform(0.05, 0.2), rng.uniform(0.3, 0.6), rng.uniform(0.7, 0.9)]))

    body = footprint_corners(xy, length, width, yaw)
    body_h = rng.uniform(0.85, 1.0)

    def spec(face, w_m, h_m):
        return TextureSpec(
            "car",
            *texture_size_px(w_m, h_m, ppm),
            texture_seed(rng),
            (("ppm", ppm), ("tone", tone), ("face", face)),
        )

    side = spec("side", length, body_h - 0.12)
    # Footprint order: rear-left, front-left, front-right, rear-right (clockwise):
    # edges: left side, front, right side, back.
    walls = [side, spec("front", width, body_h - 0.12), side, spec("back", width, body_h - 0.12)]
    top = spec("top", length, width)
    add_box(b, body, 0.12, body_h, walls, ppm, KIND_CAR, top_spec=top, reflectance=0.5)
    cab_len = length * rng.uniform(0.45, 0.6)
    cab_h = rng.uniform(0.4, 0.55)
    centre = np.asarray(xy) - 0.1 * length * np.array([math.cos(yaw), math.sin(yaw)])
    cabin = footprint_corners(centre, cab_len, width - 0.12, yaw)
    cside = spec("cabin_side", cab_len, cab_h)
    cend = spec("cabin_end", width - 0.12, cab_h)
    add_box(
        b,
        cabin,
        body_h,
        body_h + cab_h,
        [cside, cend, cside, cend],
        ppm,
        KIND_GLASS,
        top_spec=spec("top", cab_len, width - 0.12),
        reflectance=0.2,
    )

"""Buildings of a city block: frontages along a street and the buildings that fill them.

Walls reach below the ground (``WALL_FOOT_M``) so that no crack opens at their foot.

Streets repeat themselves: a district has a few building designs (a terrace house, a
chain store's shop front, a standard apartment block) that recur as rows of identical
neighbours along its streets and again on other streets, with the same facade to the
texel. Retrieval must survive that aliasing, as it must on real streets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monoloc.sim.scene import KIND_WALL
from monoloc.sim.shapes import add_wall, texture_size_px
from monoloc.sim.textures import TextureSpec, texture_seed

WALL_FOOT_M = -0.3


@dataclass(frozen=True)
class BuildingDesign:
    """A building that recurs: lot width and set-back in metres, shop front or not, and
    the seed every copy builds from (same seed, same building)."""

    width_m: float
    setback_m: float
    shops: bool
    seed: int


def building_designs(rng: np.random.Generator, config) -> tuple[BuildingDesign, ...]:
    """The ``config.building_designs`` designs of one district (never plain fronts)."""
    designs = []
    for _ in range(config.building_designs):
        width = rng.uniform(config.lot_width_m[0], 0.5 * sum(config.lot_width_m))
        designs.append(
            BuildingDesign(
                width_m=float(width),
                setback_m=float(rng.uniform(*config.setback_m)),
                shops=bool(rng.random() < config.shop_fraction),
                seed=int(rng.integers(0, 2**31)),
            )
        )
    return tuple(designs)


def add_frontage(b, rng, config, start, end, normal, max_depth, designs=()):
    """Lots of buildings along the line start->end, set back along ``normal``; a lot
    starts a row of identical copies of one of ``designs`` with probability
    ``config.repeated_building_fraction``."""
    length = float(np.linalg.norm(end - start))
    if length < 4.0:
        return
    d = (end - start) / length
    pos = 0.0
    while pos < length - 1e-6:
        if designs and rng.random() < config.repeated_building_fraction:
            design = designs[int(rng.integers(len(designs)))]
            copies = int(rng.integers(config.terrace_copies[0], config.terrace_copies[1] + 1))
            copies = min(copies, int((length - pos) // design.width_m))
            for _ in range(copies):
                depth = min(max_depth - design.setback_m, config.lot_depth_m[0])
                f0 = start + d * pos + normal * design.setback_m
                f1 = start + d * (pos + design.width_m) + normal * design.setback_m
                corners = np.array([f0, f1, f1 + normal * depth, f0 + normal * depth])
                copy_rng = np.random.default_rng(design.seed)
                add_building(
                    b,
                    copy_rng,
                    config,
                    corners,
                    front_edges=(0,),
                    height=None,
                    shops=design.shops,
                    plain_front=False,
                )
                pos += design.width_m
            if copies:
                continue
        width = rng.uniform(*config.lot_width_m)
        if length - (pos + width) < config.lot_width_m[0] * 0.6:
            width = length - pos
        if rng.random() < config.empty_lot_fraction and width < length:
            pos += width
            continue
        setback = rng.uniform(*config.setback_m)
        if rng.random() < config.deep_setback_fraction:
            setback = rng.uniform(4.0, 8.0)
        depth = min(max_depth - setback, rng.uniform(*config.lot_depth_m))
        if depth < 3.0:
            setback, depth = 0.0, max_depth
        f0 = start + d * pos + normal * setback
        f1 = start + d * (pos + width) + normal * setback
        corners = np.array([f0, f1, f1 + normal * depth, f0 + normal * depth])
        add_building(
            b,
            rng,
            config,
            corners,
            front_edges=(0,),
            height=None,
            shops=rng.random() < config.shop_fraction,
        )
        pos += width


def add_building(b, rng, config, corners, front_edges, height, shops, plain_front=None):
    """A box building on footprint ``corners`` (4, 2) (any winding); edges listed in
    ``front_edges`` (edge k = corners[k] -> corners[k+1]) get street facades, plain ones
    with probability ``config.plain_facade_fraction`` unless ``plain_front`` says."""
    ppm = config.facade_texels_per_m
    h = height if height is not None else rng.uniform(*config.building_height_m)
    if rng.random() < 0.15:
        h = rng.uniform(*config.building_height_m) * 1.6
    x, y = corners[:, 0], corners[:, 1]
    area2 = float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))
    if area2 > 0:  # counter-clockwise: reverse so that walls face outwards
        cw = corners[::-1]
        front = {(2 - e) % 4 for e in front_edges}
    else:
        cw = corners
        front = set(front_edges)
    plain = rng.random() < config.plain_facade_fraction
    plain_front = plain if plain_front is None else plain_front
    specs = []
    for k in range(4):
        length = float(np.linalg.norm(cw[(k + 1) % 4] - cw[k]))
        if k in front:
            style = "plain" if plain_front else ("shops" if shops else "windows")
            p = ppm
        else:
            style = "plain" if rng.random() < 0.5 else "windows"
            p = ppm * 0.6
        w, hh = texture_size_px(length, h - WALL_FOOT_M, p)
        specs.append(
            (TextureSpec("facade", w, hh, texture_seed(rng), (("ppm", p), ("style", style))), p)
        )
    for k in range(4):
        spec, p = specs[k]
        add_wall(
            b,
            cw[k],
            cw[(k + 1) % 4],
            WALL_FOOT_M,
            h,
            spec,
            p,
            KIND_WALL,
            max_piece_m=6.0,
            reflectance=0.35,
        )

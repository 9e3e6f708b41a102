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
    """A street facade that recurs: a module of ``module_width_m`` (tiled along the
    wall), the building's height, shop front or not, and the seed of its texture (same
    seed, same facade to the texel)."""

    module_width_m: float
    height_m: float
    shops: bool
    seed: int

    def front_spec(self, ppm: float) -> TextureSpec:
        """The facade texture every copy shows (tiles along a wider wall)."""
        w, h = texture_size_px(self.module_width_m, self.height_m - WALL_FOOT_M, ppm)
        style = "shops" if self.shops else "windows"
        return TextureSpec("facade", w, h, self.seed, (("ppm", ppm), ("style", style)), wrap=True)


def building_designs(rng: np.random.Generator, config) -> tuple[BuildingDesign, ...]:
    """The ``config.building_designs`` recurring facades of one district."""
    return tuple(
        BuildingDesign(
            module_width_m=float(rng.uniform(6.0, 12.0)),
            height_m=float(rng.uniform(*config.building_height_m)),
            shops=bool(rng.random() < config.shop_fraction),
            seed=texture_seed(rng),
        )
        for _ in range(config.building_designs)
    )


def add_frontage(b, rng, config, start, end, normal, max_depth, designs=(), design_rng=None):
    """Lots of buildings along the line start->end, set back along ``normal``. With
    ``designs``, a lot starts a row of ``config.terrace_copies`` neighbours that show the
    same recurring facade with probability ``config.repeated_building_fraction`` (drawn
    from ``design_rng``, so that the lots themselves do not depend on it)."""
    length = float(np.linalg.norm(end - start))
    if length < 4.0:
        return
    d = (end - start) / length
    pos = 0.0
    design, copies_left = None, 0
    while pos < length - 1e-6:
        width = rng.uniform(*config.lot_width_m)
        if length - (pos + width) < config.lot_width_m[0] * 0.6:
            width = length - pos
        if rng.random() < config.empty_lot_fraction and width < length:
            pos += width
            copies_left = 0  # a gap ends a row
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
        if copies_left == 0 and designs and design_rng.random() < config.repeated_building_fraction:
            design = designs[int(design_rng.integers(len(designs)))]
            copies_left = int(
                design_rng.integers(config.terrace_copies[0], config.terrace_copies[1] + 1)
            )
        add_building(
            b,
            rng,
            config,
            corners,
            front_edges=(0,),
            height=None,
            shops=rng.random() < config.shop_fraction,
            front_design=design if copies_left > 0 else None,
        )
        copies_left = max(0, copies_left - 1)
        pos += width


def add_building(b, rng, config, corners, front_edges, height, shops, front_design=None):
    """A box building on footprint ``corners`` (4, 2) (any winding); edges listed in
    ``front_edges`` (edge k = corners[k] -> corners[k+1]) get street facades: those of
    ``front_design`` (a :class:`BuildingDesign`, which also sets the height) if given.
    ``rng`` is drawn from the same way either way."""
    ppm = config.facade_texels_per_m
    h = height if height is not None else rng.uniform(*config.building_height_m)
    if rng.random() < 0.15:
        h = rng.uniform(*config.building_height_m) * 1.6
    if front_design is not None:
        h = front_design.height_m
    x, y = corners[:, 0], corners[:, 1]
    area2 = float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))
    if area2 > 0:  # counter-clockwise: reverse so that walls face outwards
        cw = corners[::-1]
        front = {(2 - e) % 4 for e in front_edges}
    else:
        cw = corners
        front = set(front_edges)
    plain_front = rng.random() < config.plain_facade_fraction
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
        spec = TextureSpec("facade", w, hh, texture_seed(rng), (("ppm", p), ("style", style)))
        if k in front and front_design is not None:
            spec = front_design.front_spec(p)
        specs.append((spec, p))
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

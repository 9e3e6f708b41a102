"""Furniture of an indoor room, as textured boxes: shelving units, cabinets and lockers
against the walls (fronts painted like the wall sections of ``monoloc.sim.indoor.wall_textures``),
boxes, crates, bins and chairs on the floor along the walls. The infield and the
obstacles beside the track are in ``monoloc.sim.indoor.infield``.
"""

from __future__ import annotations

import math

import numpy as np

from monoloc.sim.scene import KIND_WALL, SceneBuilder
from monoloc.sim.shapes import add_box, add_split_quad, footprint_corners, texture_size_px
from monoloc.sim.textures import TextureSpec, texture_seed

_FRONT_PPM = 300.0
_SIDE_PPM = 250.0


def _surface(rng, width_m, height_m, style, ppm=_SIDE_PPM) -> TextureSpec:
    return TextureSpec(
        "indoor_surface",
        *texture_size_px(width_m, height_m, ppm),
        seed=texture_seed(rng),
        params=(("ppm", ppm), ("style", style)),
    )


def _front(rng, width_m, height_m, style, tone) -> TextureSpec:
    return TextureSpec(
        "indoor_wall",
        *texture_size_px(width_m, height_m, _FRONT_PPM),
        seed=texture_seed(rng),
        params=(
            ("ppm", _FRONT_PPM),
            ("paint", round(float(tone), 4)),
            ("sections", ((style, 0.0, round(width_m, 4)),)),
            ("skirting", False),
        ),
    )


def add_textured_box(
    b, rng, centre_xy, yaw, depth_m, width_m, z0, z1, front, side_style, kind=KIND_WALL, top=True
) -> None:
    """A box with ``front`` (a TextureSpec or None) on the face looking along ``yaw``."""
    corners = footprint_corners(centre_xy, depth_m, width_m, yaw)
    h = z1 - z0
    specs = [
        _surface(rng, depth_m, h, side_style),
        front or _surface(rng, width_m, h, side_style),
        _surface(rng, depth_m, h, side_style),
        _surface(rng, width_m, h, side_style),
    ]
    ppm = _FRONT_PPM if front is not None else _SIDE_PPM
    top_spec = _surface(rng, depth_m, width_m, side_style) if top else None
    add_box(b, corners, z0, z1, specs, ppm, kind, top_spec=top_spec, max_piece_m=0.6)


def add_underside(b, rng, corners, z, style) -> None:
    """A downward-facing rectangle on a footprint (table tops seen from a low camera)."""
    c0, c1, c3 = corners[0], corners[1], corners[3]
    u = np.array([*(c1 - c0), 0.0])
    v = np.array([*(c3 - c0), 0.0])
    lu, lv = float(np.linalg.norm(u)), float(np.linalg.norm(v))
    u, v = u / lu, v / lv
    origin = np.array([*c0, z])
    if np.cross(v, u)[2] > 0:  # front face must look down
        v, origin = -v, np.array([*c3, z])
    add_split_quad(b, origin, u, v, lu, lv, _surface(rng, lu, lv, style), _SIDE_PPM, KIND_WALL)


def add_furniture(b: SceneBuilder, rng, config, track, walls) -> None:
    """Units against the walls in front of suitable sections, and infield objects."""
    candidates = [
        (w, s)
        for w in walls
        for s in w.sections
        if s[0] in ("shelf", "cabinet", "lockers", "poster", "storage")
    ]
    order = rng.permutation(len(candidates))[: config.furniture]
    used: dict[int, list[tuple[float, float]]] = {}
    for i in order:
        wall, (style, x0, x1) = candidates[int(i)]
        kind = {"shelf": "shelf", "cabinet": "cabinet", "lockers": "lockers"}.get(
            style, str(rng.choice(["shelf", "cabinet", "lockers"]))
        )
        width = min(x1 - x0 - 0.12, rng.uniform(0.8, 1.6))
        if width < 0.5:
            continue
        height = {
            "shelf": rng.uniform(1.2, 1.9),
            "cabinet": rng.uniform(0.75, 0.95),
            "lockers": rng.uniform(1.7, 1.9),
        }[kind]
        depth = {"shelf": 0.38, "cabinet": 0.55, "lockers": 0.45}[kind]
        lo = x0 + width / 2 + 0.05
        xc = rng.uniform(lo, max(lo, x1 - width / 2 - 0.05))
        inward = wall.inward
        centre = wall.point(xc) + inward * (0.02 + depth / 2)
        yaw = math.atan2(inward[1], inward[0])
        tone = rng.uniform(0.25, 0.85)
        side = "metal" if kind == "lockers" else "wood"
        add_textured_box(
            b,
            rng,
            centre,
            yaw,
            depth,
            width,
            0.0,
            height,
            _front(rng, width, height, kind, tone),
            side,
        )
        used.setdefault(id(wall), []).append((xc - width / 2, xc + width / 2))
    _wall_clutter(b, rng, config, walls, used)


def _wall_clutter(b, rng, config, walls, used) -> None:
    """Boxes, crates and bins standing on the floor against the (not bare) walls."""
    for wall in walls:
        for style, x0, x1 in wall.sections:
            if style in ("plain", "door"):
                continue
            x = x0 + rng.uniform(0.0, 0.5)
            while x < x1 - 0.3:
                width = rng.uniform(0.25, 0.6)
                if (
                    x + width > x1
                    or rng.random() < 0.3
                    or any(
                        a - 0.05 < x + width and x < b_ + 0.05 for a, b_ in used.get(id(wall), [])
                    )
                ):
                    x += width
                    continue
                depth, height = rng.uniform(0.25, 0.45), rng.uniform(0.2, 0.65)
                inward = wall.inward
                if rng.random() < 0.15:
                    centre = wall.point(x + width / 2) + inward * 0.3
                    add_chair(b, rng, centre, math.atan2(inward[1], inward[0]) + rng.normal(0, 0.2))
                    x += 0.6
                    continue
                centre = wall.point(x + width / 2) + inward * (0.03 + depth / 2)
                yaw = math.atan2(inward[1], inward[0]) + rng.normal(0, 0.08)
                front = None
                if rng.random() < 0.4:
                    front = _front(rng, width, height, "storage", rng.uniform(0.3, 0.8))
                add_textured_box(
                    b,
                    rng,
                    centre,
                    yaw,
                    depth,
                    width,
                    0.0,
                    height,
                    front,
                    str(rng.choice(["cardboard", "cardboard", "metal", "foam"])),
                )
                x += width + rng.uniform(0.05, 0.4)


def add_chair(b, rng, centre_xy, yaw) -> None:
    """A four-legged chair (seat, back, legs) facing ``yaw``."""
    seat, height = rng.uniform(0.4, 0.46), rng.uniform(0.43, 0.48)
    style = str(rng.choice(["wood", "metal", "foam"]))
    add_textured_box(b, rng, centre_xy, yaw, seat, seat, height - 0.04, height, None, style)
    corners = footprint_corners(centre_xy, seat, seat, yaw)
    add_underside(b, rng, corners, height - 0.04, style)
    p = np.asarray(centre_xy, dtype=np.float64)
    for c in corners:
        add_textured_box(
            b,
            rng,
            p + (c - p) * 0.85,
            yaw,
            0.025,
            0.025,
            0.0,
            height - 0.04,
            None,
            "metal",
            top=False,
        )
    back = p - np.array([math.cos(yaw), math.sin(yaw)]) * (seat / 2 - 0.01)
    add_textured_box(
        b, rng, back, yaw, 0.02, seat, height, height + rng.uniform(0.35, 0.45), None, style
    )

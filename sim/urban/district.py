"""Builds one district's static scene: ground, roads, sidewalks, and (through
``monoloc.sim.urban.buildings`` and ``monoloc.sim.urban.street_props``) buildings and
street furniture.

Heights: carriageway at z = 0, sidewalks and block interiors at the kerb height; walls
reach below the ground so that no crack opens at their foot.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from monoloc.sim.scene import KIND_GROUND, KIND_ROAD, KIND_WALL, Scene, SceneBuilder
from monoloc.sim.shapes import add_split_quad, add_wall, texture_size_px
from monoloc.sim.textures import TextureSpec, texture_seed
from monoloc.sim.urban.buildings import (
    WALL_FOOT_M,
    add_building,
    add_frontage,
    building_designs,
)
from monoloc.sim.urban.street_props import add_street_furniture

KERB_M = 0.12
UPV = np.array([0.0, 0.0, 1.0])


def _ground_rect(builder, x0, y0, x1, y1, z, kind_name, ppm, rng, kind, piece=8.0, **params):
    """An axis-aligned horizontal rectangle facing up, with its own texture."""
    if x1 - x0 < 0.05 or y1 - y0 < 0.05:
        return
    w, h = texture_size_px(x1 - x0, y1 - y0, ppm)
    spec = TextureSpec(kind_name, w, h, texture_seed(rng), (("ppm", ppm),) + tuple(params.items()))
    add_split_quad(
        builder,
        (x0, y1, z),
        (1, 0, 0),
        (0, -1, 0),
        x1 - x0,
        y1 - y0,
        spec,
        ppm,
        kind,
        max_piece_m=piece,
        reflectance=0.25,
    )


def _road_segment(builder, a_xy, b_xy, width, ppm, rng):
    """Carriageway from a to b (already trimmed to the intersections), texture x along."""
    d = np.array([b_xy[0] - a_xy[0], b_xy[1] - a_xy[1], 0.0])
    length = float(np.linalg.norm(d))
    d /= length
    left = np.cross(UPV, d)
    origin = np.array([a_xy[0], a_xy[1], 0.0]) + left * width / 2
    w, h = texture_size_px(length, width, ppm)
    params = (
        ("ppm", ppm),
        ("cross_start", bool(rng.random() < 0.3)),
        ("cross_end", bool(rng.random() < 0.3)),
        ("edge_lines", bool(rng.random() < 0.3)),
    )
    spec = TextureSpec("road", w, h, texture_seed(rng), params)
    add_split_quad(
        builder,
        origin,
        d,
        -left,
        length,
        width,
        spec,
        ppm,
        KIND_ROAD,
        max_piece_m=7.0,
        reflectance=0.15,
    )


def build_district_scene(grid, config, seed: int) -> tuple[Scene, np.ndarray]:
    """Static scene of one district and its parking spots (N, 3) of (x, y, yaw_rad)."""
    rng = np.random.default_rng(seed)
    # Recurring facades draw from their own generator: the lots stay where they were.
    design_rng = np.random.default_rng([seed, 1])
    designs = (building_designs(design_rng, config), design_rng)
    b = SceneBuilder()
    gppm = config.ground_texels_per_m
    xs, ys = grid.xs, grid.ys
    # Ground far outside the district (beyond the outer ring of buildings), seen through
    # gaps; four rectangles around the district rather than one plane under everything.
    base = TextureSpec("asphalt", 256, 256, texture_seed(rng), (("ppm", gppm),), wrap=True)
    inner, outer = 20.0, 250.0
    bx0, by0, bx1, by1 = xs[0] - inner, ys[0] - inner, xs[-1] + inner, ys[-1] + inner
    for rx0, ry0, rx1, ry1 in (
        (bx0 - outer, by0 - outer, bx1 + outer, by0),
        (bx0 - outer, by1, bx1 + outer, by1 + outer),
        (bx0 - outer, by0, bx0, by1),
        (bx1, by0, bx1 + outer, by1),
    ):
        add_split_quad(
            b,
            (rx0, ry1, -0.05),
            (1, 0, 0),
            (0, -1, 0),
            rx1 - rx0,
            ry1 - ry0,
            base,
            gppm,
            KIND_GROUND,
            max_piece_m=40.0,
            reflectance=0.15,
        )
    hx, hy = grid.road_w_x / 2, grid.road_w_y / 2
    for i in range(len(xs)):
        for j in range(len(ys)):
            _ground_rect(
                b,
                xs[i] - hx[i],
                ys[j] - hy[j],
                xs[i] + hx[i],
                ys[j] + hy[j],
                0.0,
                "asphalt",
                gppm,
                rng,
                KIND_ROAD,
                piece=6.0,
            )
    for j in range(len(ys)):
        for i in range(len(xs) - 1):
            _road_segment(
                b,
                (xs[i] + hx[i], ys[j]),
                (xs[i + 1] - hx[i + 1], ys[j]),
                grid.road_w_y[j],
                gppm,
                rng,
            )
    for i in range(len(xs)):
        for j in range(len(ys) - 1):
            _road_segment(
                b,
                (xs[i], ys[j] + hy[j]),
                (xs[i], ys[j + 1] - hy[j + 1]),
                grid.road_w_x[i],
                gppm,
                rng,
            )
    spots: list[np.ndarray] = []
    for i in range(len(xs) - 1):
        for j in range(len(ys) - 1):
            kerb = (xs[i] + hx[i], ys[j] + hy[j], xs[i + 1] - hx[i + 1], ys[j + 1] - hy[j + 1])
            side = (grid.side_w_x[i], grid.side_w_y[j], grid.side_w_x[i + 1], grid.side_w_y[j + 1])
            _block(b, rng, config, kerb, side, (True, True, True, True), designs)
    _outer_ring(b, rng, config, grid, designs)
    _parking_spots(grid, spots)
    return b.build(), np.concatenate(spots).reshape(-1, 3) if spots else np.zeros((0, 3))


def _outer_ring(b, rng, config, grid, designs):
    """Buildings facing the perimeter streets from outside, and corner buildings."""
    xs, ys = grid.xs, grid.ys
    hx, hy = grid.road_w_x / 2, grid.road_w_y / 2
    depth = 28.0
    kx0, kx1 = xs[0] - hx[0], xs[-1] + hx[-1]
    ky0, ky1 = ys[0] - hy[0], ys[-1] + hy[-1]
    # (kerb rect, sidewalk widths (w, s, e, n), which sides face a street)
    strips = [
        ((kx0, ky0 - depth, kx1, ky0), (0, 0, 0, grid.side_w_y[0]), (False, False, False, True)),
        ((kx0, ky1, kx1, ky1 + depth), (0, grid.side_w_y[-1], 0, 0), (False, True, False, False)),
        ((kx0 - depth, ky0, kx0, ky1), (0, 0, grid.side_w_x[0], 0), (False, False, True, False)),
        ((kx1, ky0, kx1 + depth, ky1), (grid.side_w_x[-1], 0, 0, 0), (True, False, False, False)),
    ]
    outer = replace(config, empty_lot_fraction=0.0)  # no gaps onto the city's edge
    for kerb, side, facing in strips:
        _block(b, rng, outer, kerb, side, facing, designs)
    _backdrop(b, rng, config, (kx0 - depth, ky0 - depth, kx1 + depth, ky1 + depth))
    for cx, cy in ((kx0 - depth, ky0 - depth), (kx1, ky0 - depth), (kx0 - depth, ky1), (kx1, ky1)):
        corners = np.array([[cx, cy + depth], [cx + depth, cy + depth], [cx + depth, cy], [cx, cy]])
        add_building(b, rng, config, corners, front_edges=(0, 1, 2, 3), height=None, shops=False)


def _backdrop(b, rng, config, inner_rect):
    """A ring of tall, coarsely textured buildings around ``inner_rect`` so that no view
    out of the district ends at an empty horizon."""
    x0, y0, x1, y1 = inner_rect
    ppm = config.facade_texels_per_m * 0.4
    depth = 15.0
    for ax, ay, bx, by, nx, ny in (
        (x0 - depth, y0 - depth, x1 + depth, y0 - depth, 0.0, 1.0),
        (x1 + depth, y1 + depth, x0 - depth, y1 + depth, 0.0, -1.0),
        (x0 - depth, y1 + depth, x0 - depth, y0 - depth, 1.0, 0.0),
        (x1 + depth, y0 - depth, x1 + depth, y1 + depth, -1.0, 0.0),
    ):
        start, end = np.array([ax, ay]), np.array([bx, by])
        length = float(np.linalg.norm(end - start))
        d, n = (end - start) / length, np.array([nx, ny])
        pos = 0.0
        while pos < length - 1.0:
            w = min(length - pos, rng.uniform(20.0, 45.0))
            f0 = start + d * pos + n * rng.uniform(0.0, 4.0)
            f1 = f0 + d * w
            corners = np.array([f0, f1, f1 - n * depth, f0 - n * depth])
            h = rng.uniform(15.0, 40.0)
            spec = TextureSpec(
                "facade",
                *texture_size_px(w, h - WALL_FOOT_M, ppm),
                texture_seed(rng),
                (("ppm", ppm), ("style", "windows")),
            )
            x, y = corners[:, 0], corners[:, 1]
            area2 = float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))
            cw = corners if area2 < 0 else corners[::-1]
            for k in range(4):
                add_wall(
                    b,
                    cw[k],
                    cw[(k + 1) % 4],
                    WALL_FOOT_M,
                    h,
                    spec,
                    ppm,
                    KIND_WALL,
                    max_piece_m=12.0,
                    reflectance=0.35,
                )
            pos += w


def _block(b, rng, config, kerb, side, facing, designs):
    """A block inside kerb rect (x0, y0, x1, y1): kerb faces, sidewalks of widths
    (west, south, east, north) on the sides that face a street, interior, buildings
    (some showing the district's recurring facades: ``designs`` = (designs, their
    generator))."""
    x0, y0, x1, y1 = kerb
    sw, ss, se, sn = (s if f else 0.0 for s, f in zip(side, facing, strict=True))
    gppm = config.ground_texels_per_m
    # Kerb faces (clockwise walk = outward faces), only towards streets.
    ring = [(x0, y1), (x1, y1), (x1, y0), (x0, y0)]
    sides_cw = (3, 2, 1, 0)  # edge k of the ring faces: north, east, south, west
    for k in range(4):
        if facing[sides_cw[k]]:
            spec = TextureSpec(
                "kerb",
                *texture_size_px(math.dist(ring[k], ring[(k + 1) % 4]), 0.25, gppm),
                texture_seed(rng),
                (("ppm", gppm),),
            )
            add_wall(
                b,
                ring[k],
                ring[(k + 1) % 4],
                -0.1,
                KERB_M + 0.0,
                spec,
                gppm,
                KIND_GROUND,
                max_piece_m=7.0,
                reflectance=0.3,
            )
    # Sidewalks: south and north full width, west and east between them.
    z = KERB_M
    if ss:
        _ground_rect(b, x0, y0, x1, y0 + ss, z, "sidewalk", gppm, rng, KIND_GROUND)
    if sn:
        _ground_rect(b, x0, y1 - sn, x1, y1, z, "sidewalk", gppm, rng, KIND_GROUND)
    if sw:
        _ground_rect(b, x0, y0 + ss, x0 + sw, y1 - sn, z, "sidewalk", gppm, rng, KIND_GROUND)
    if se:
        _ground_rect(b, x1 - se, y0 + ss, x1, y1 - sn, z, "sidewalk", gppm, rng, KIND_GROUND)
    lx0, ly0, lx1, ly1 = x0 + sw, y0 + ss, x1 - se, y1 - sn
    _ground_rect(b, lx0, ly0, lx1, ly1, z, "lawn", gppm * 0.5, rng, KIND_GROUND, piece=12.0)
    # Frontages: (start, end, inward normal) along each street-facing side.
    max_depth = min(config.lot_depth_m[1], (lx1 - lx0) / 2, (ly1 - ly0) / 2)
    corner = min(max_depth, rng.uniform(*config.lot_depth_m))
    fronts = []  # (start, end, inward normal, sidewalk width)
    cs = corner if facing[1] else 0.0
    cn = corner if facing[3] else 0.0
    if facing[1]:
        fronts.append(((lx0, ly0), (lx1, ly0), (0.0, 1.0), ss))
    if facing[3]:
        fronts.append(((lx1, ly1), (lx0, ly1), (0.0, -1.0), sn))
    if facing[0]:
        fronts.append(((lx0, ly1 - cn), (lx0, ly0 + cs), (1.0, 0.0), sw))
    if facing[2]:
        fronts.append(((lx1, ly0 + cs), (lx1, ly1 - cn), (-1.0, 0.0), se))
    for start, end, normal, _ in fronts:
        add_frontage(
            b,
            rng,
            config,
            np.array(start),
            np.array(end),
            np.array(normal),
            max(6.0, max_depth),
            *designs,
        )
    for start, end, normal, walk_w in fronts:
        add_street_furniture(
            b, rng, config, np.array(start), np.array(end), np.array(normal), z, walk_w
        )


def _parking_spots(grid, spots):
    """Car centres along the parking lanes of streets that have them."""
    for j in range(len(grid.ys)):
        for i in range(len(grid.xs) - 1):
            if grid.parking_y[j]:
                a, bb = grid.xs[i] + grid.road_w_x[i] / 2, grid.xs[i + 1] - grid.road_w_x[i + 1] / 2
                off = grid.road_w_y[j] / 2 - 1.2
                for x in np.arange(a + 8.0, bb - 8.0, 6.0):
                    spots.append(
                        np.array([[x, grid.ys[j] - off, 0.0], [x, grid.ys[j] + off, np.pi]])
                    )
    for i in range(len(grid.xs)):
        for j in range(len(grid.ys) - 1):
            if grid.parking_x[i]:
                a, bb = grid.ys[j] + grid.road_w_y[j] / 2, grid.ys[j + 1] - grid.road_w_y[j + 1] / 2
                off = grid.road_w_x[i] / 2 - 1.2
                for y in np.arange(a + 8.0, bb - 8.0, 6.0):
                    spots.append(
                        np.array(
                            [[grid.xs[i] + off, y, np.pi / 2], [grid.xs[i] - off, y, -np.pi / 2]]
                        )
                    )

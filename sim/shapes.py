"""Scenario-independent shapes made of quads: split rectangles, walls, boxes, billboards.

Large rectangles are cut into pieces that share one texture (continuous texture
coordinates, so no visible seam) so that each piece gets its own mip level: a long wall
seen at a grazing angle is sharp near the camera and does not alias far away.
"""

from __future__ import annotations

import math

import numpy as np

from monoloc.sim.scene import SceneBuilder
from monoloc.sim.textures import TextureSpec

UP = np.array([0.0, 0.0, 1.0])
DOWN = -UP


def texture_size_px(size_u_m: float, size_v_m: float, ppm: float) -> tuple[int, int]:
    """(width_px, height_px) of a texture covering size_u x size_v metres at ``ppm``."""
    return max(2, math.ceil(size_u_m * ppm)), max(2, math.ceil(size_v_m * ppm))


def add_split_quad(
    builder: SceneBuilder,
    origin,
    axis_u,
    axis_v,
    size_u: float,
    size_v: float,
    spec: TextureSpec,
    ppm: float,
    kind: int,
    max_piece_m: float = 8.0,
    reflectance: float = 0.3,
    two_sided: bool = False,
    max_piece_v_m: float | None = None,
) -> None:
    """A rectangle cut into pieces of at most ``max_piece_m`` along u and
    ``max_piece_v_m`` (default the same) along v, all sharing ``spec`` with texture
    (0, 0) at ``origin``."""
    tex = builder.texture(spec)
    origin = np.asarray(origin, dtype=np.float64)
    axis_u = np.asarray(axis_u, dtype=np.float64)
    axis_v = np.asarray(axis_v, dtype=np.float64)
    nu = max(1, math.ceil(size_u / max_piece_m - 1e-9))
    nv = max(1, math.ceil(size_v / (max_piece_v_m or max_piece_m) - 1e-9))
    du, dv = size_u / nu, size_v / nv
    for i in range(nu):
        for j in range(nv):
            builder.add_quad(
                origin + i * du * axis_u + j * dv * axis_v,
                axis_u,
                axis_v,
                du,
                dv,
                tex,
                ppm,
                kind,
                tex_offset_px=(i * du * ppm, j * dv * ppm),
                reflectance=reflectance,
                two_sided=two_sided,
            )


def add_wall(
    builder: SceneBuilder,
    a_xy,
    b_xy,
    z_bottom: float,
    z_top: float,
    spec: TextureSpec,
    ppm: float,
    kind: int,
    max_piece_m: float = 6.0,
    reflectance: float = 0.3,
    two_sided: bool = False,
) -> None:
    """A vertical wall from ground point a to b; its front face is on the left of a->b
    (walk a box's footprint clockwise seen from above for outward faces). Seen from the
    front, texture column 0 is at b and row 0 at ``z_top``."""
    b = np.array([b_xy[0], b_xy[1], z_top], dtype=np.float64)
    d = np.array([a_xy[0] - b_xy[0], a_xy[1] - b_xy[1], 0.0])
    length = float(np.linalg.norm(d))
    # Walls are cut only into vertical strips: along a strip the distance to a camera on
    # the street hardly varies.
    add_split_quad(
        builder,
        b,
        d / length,
        DOWN,
        length,
        z_top - z_bottom,
        spec,
        ppm,
        kind,
        max_piece_m=max_piece_m,
        reflectance=reflectance,
        two_sided=two_sided,
        max_piece_v_m=1e9,
    )


def footprint_corners(centre_xy, length_m: float, width_m: float, yaw_rad: float) -> np.ndarray:
    """(4, 2) corners of a rectangle (length along yaw), clockwise seen from above,
    starting at the rear-left corner."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    fwd, left = np.array([c, s]), np.array([-s, c])
    centre = np.asarray(centre_xy, dtype=np.float64)
    hl, hw = length_m / 2, width_m / 2
    return np.array(
        [
            centre - hl * fwd + hw * left,
            centre + hl * fwd + hw * left,
            centre + hl * fwd - hw * left,
            centre - hl * fwd - hw * left,
        ]
    )


def add_box(
    builder: SceneBuilder,
    corners_xy: np.ndarray,
    z_bottom: float,
    z_top: float,
    wall_specs: list[TextureSpec],
    ppm: float,
    kind: int,
    top_spec: TextureSpec | None = None,
    max_piece_m: float = 6.0,
    reflectance: float = 0.3,
) -> None:
    """A box on a clockwise (4, 2) footprint: four walls (wall_specs[i] for the edge
    corners[i] -> corners[i+1]) and an optional top."""
    for i in range(4):
        add_wall(
            builder,
            corners_xy[i],
            corners_xy[(i + 1) % 4],
            z_bottom,
            z_top,
            wall_specs[i],
            ppm,
            kind,
            max_piece_m=max_piece_m,
            reflectance=reflectance,
        )
    if top_spec is not None:
        # Top face: origin at corner 0, u along edge 0->1, v along 0->3 (normal up).
        c0, c1, c3 = corners_xy[0], corners_xy[1], corners_xy[3]
        u = np.array([*(c1 - c0), 0.0])
        v = np.array([*(c3 - c0), 0.0])
        lu, lv = float(np.linalg.norm(u)), float(np.linalg.norm(v))
        u, v = u / lu, v / lv
        if np.cross(v, u)[2] < 0:
            v = -v
            origin = np.array([*c3, z_top])
        else:
            origin = np.array([*c0, z_top])
        add_split_quad(
            builder,
            origin,
            u,
            v,
            lu,
            lv,
            top_spec,
            ppm,
            kind,
            max_piece_m=max_piece_m,
            reflectance=reflectance,
        )


def add_billboard(
    builder: SceneBuilder,
    centre,
    yaw_rad: float,
    width_m: float,
    height_m: float,
    spec: TextureSpec,
    ppm: float,
    kind: int,
    reflectance: float = 0.3,
) -> None:
    """A vertical, two-sided rectangle centred at ``centre`` (3,), facing ``yaw_rad``."""
    u = np.array([-math.sin(yaw_rad), math.cos(yaw_rad), 0.0])
    centre = np.asarray(centre, dtype=np.float64)
    origin = centre - u * width_m / 2 + UP * height_m / 2
    tex = builder.texture(spec)
    builder.add_quad(
        origin, u, DOWN, width_m, height_m, tex, ppm, kind, reflectance=reflectance, two_sided=True
    )

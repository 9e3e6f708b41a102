"""Indoor wall textures: painted walls with sections of shelves, cabinets, doors, posters,
whiteboards, windows, pegboards, lockers, storage bins, exposed brick, or nothing at all
(the featureless walls that are the method's hard case).

Photographs (scikit-image samples) give posters, pictures, window views and brick; the
rest is drawn. A 1:10 car's camera sits 17 cm above the floor, so most sections put
detail low on the wall (skirting boards, sockets, radiators, bottom shelves, bins).
``wall`` takes ``params``: length_m, height_m, ppm, paint (tone), skirting (bool) and
sections ((style, x0_m, x1_m), ...) with x from the wall's left end seen from the room.
"""

from __future__ import annotations

import numpy as np

from monoloc.sim.indoor.canvas import BOARD_LINES, Canvas, word
from monoloc.sim.indoor.units import (
    cabinet,
    lockers,
    low_clutter,
    posters,
    radiator,
    shelf,
    socket,
    storage,
)
from monoloc.sim.texture_tools import material, smooth_noise, to_uint8
from monoloc.sim.textures import TextureLayers, TextureSpec

WALL_STYLES = (
    "shelf",
    "cabinet",
    "door",
    "poster",
    "whiteboard",
    "window",
    "pegboard",
    "lockers",
    "storage",
    "brick",
    "plain",
)


def _paint(rng, w, h, ppm, tone) -> np.ndarray:
    """Emulsion paint: a roller texture too faint for ORB, and gentle shading."""
    roller = material(rng, ("gravel", "moon"), w, h, int(0.6 * ppm)) * 0.006
    return (tone * (1.0 + 0.025 * smooth_noise(rng, w, h, 1.5 * ppm) + roller)).astype(np.float32)


def _door(c: Canvas, rng, x0, x1):
    w = min(rng.uniform(0.85, 1.0), x1 - x0 - 0.1)
    dx = x0 + (x1 - x0 - w) / 2
    frame, tone = rng.uniform(0.1, 0.95), rng.uniform(0.15, 0.8)
    c.rect(dx - 0.06, 0.0, dx + w + 0.06, 2.1, frame)
    c.rect(dx, 0.0, dx + w, 2.04, tone)
    c.rect(dx + 0.02, 0.0, dx + w - 0.02, 0.22, 0.7)  # kick plate
    c.region(dx + 0.02, 0.0, dx + w - 0.02, 0.22)[:] += 0.05 * smooth_noise(
        rng, *c.region(dx + 0.02, 0.0, dx + w - 0.02, 0.22).shape[::-1], 3.0
    )
    c.rect(dx + w - 0.14, 1.02, dx + w - 0.02, 1.05, 0.85)  # handle
    c.rect(dx + w - 0.09, 0.93, dx + w - 0.07, 0.97, 0.1)  # lock
    if rng.random() < 0.5:  # vision panel
        c.rect(dx + w * 0.3, 1.25, dx + w * 0.7, 1.85, 0.1)
        c.photo(rng, dx + w * 0.3 + 0.01, 1.26, dx + w * 0.7 - 0.01, 1.84, 0.05, 0.5)
    zs = 1.55 if rng.random() < 0.5 else 1.1  # door sign
    c.rect(dx + w * 0.2, zs, dx + w * 0.8, zs + 0.1, 0.93)
    c.text(rng, word(rng), dx + w * 0.22, zs, dx + w * 0.78, zs + 0.1, 0.08)
    c.rect(dx - 0.16, 1.0, dx - 0.08, 1.12, 0.92)  # light switch
    c.rect(dx + w + 0.05, 0.0, dx + w + 0.09, 0.06, 0.2)  # door stop


def _whiteboard(c: Canvas, rng, x0, x1):
    import cv2

    bx0, bx1 = x0 + 0.1, x1 - 0.1
    z0, z1 = rng.uniform(0.8, 0.95), min(c.height_m - 0.2, rng.uniform(1.9, 2.1))
    c.rect(bx0 - 0.02, z0 - 0.02, bx1 + 0.02, z1 + 0.02, 0.6)
    c.rect(bx0, z0, bx1, z1, 0.94)
    z = z1 - 0.08
    while z > z0 + 0.12:
        lw = (bx1 - bx0) * rng.uniform(0.3, 0.8)
        lx = bx0 + rng.uniform(0.03, max(0.04, bx1 - bx0 - lw))
        c.text(
            rng,
            BOARD_LINES[int(rng.integers(len(BOARD_LINES)))],
            lx,
            z - 0.07,
            lx + lw,
            z,
            rng.choice([0.1, 0.3, 0.45]),
            0.08,
        )
        z -= rng.uniform(0.1, 0.2)
    for _ in range(int(rng.integers(1, 4))):  # a sketch: a closed curve and an arrow
        cx, cz = rng.uniform(bx0 + 0.2, bx1 - 0.1), rng.uniform(z0 + 0.2, z1 - 0.2)
        axes = (c.col(rng.uniform(0.05, 0.2)), c.col(rng.uniform(0.04, 0.15)))
        cv2.ellipse(
            c.img,
            (c.col(cx), c.row(cz)),
            axes,
            float(rng.uniform(0, 180)),
            0,
            360,
            0.2,
            max(1, c.col(0.006)),
            cv2.LINE_AA,
        )
    c.rect(bx0, z0 - 0.05, bx1, z0 - 0.02, 0.5)  # pen tray
    socket(c, x0 + 0.2, 0.3)


def _window(c: Canvas, rng, x0, x1):
    sill, top = rng.uniform(0.85, 1.0), min(c.height_m - 0.15, rng.uniform(2.0, 2.3))
    c.rect(x0 + 0.05, sill - 0.04, x1 - 0.05, top + 0.05, 0.85)
    c.photo(rng, x0 + 0.1, sill, x1 - 0.1, top, 0.2, 1.0)
    slat = rng.uniform(0.025, 0.05)
    down = top - rng.uniform(0.2, top - sill)
    z = top
    while z > down:
        c.rect(x0 + 0.1, z - slat * 0.8, x1 - 0.1, z, rng.uniform(0.7, 0.8))
        z -= slat
    c.rect(x0 + 0.03, sill - 0.06, x1 - 0.03, sill - 0.02, 0.9)
    radiator(c, rng, x0 + 0.15, x1 - 0.15)


def _pegboard(c: Canvas, rng, x0, x1):
    z0, z1 = rng.uniform(0.25, 0.5), rng.uniform(1.4, 1.9)
    tone = rng.uniform(0.45, 0.8)
    c.rect(x0 + 0.05, z0, x1 - 0.05, z1, tone)
    region = c.region(x0 + 0.05, z0, x1 - 0.05, z1)
    step = max(3, c.col(0.025))
    region[step // 2 :: step, step // 2 :: step] = tone * 0.3
    for _ in range(int((x1 - x0) * 6)):  # tool silhouettes: handle + head
        x, z = rng.uniform(x0 + 0.1, x1 - 0.15), rng.uniform(z0 + 0.1, z1 - 0.3)
        ht = rng.uniform(0.02, 0.3)
        c.rect(x, z, x + rng.uniform(0.015, 0.03), z + rng.uniform(0.1, 0.22), ht)
        c.rect(x - 0.03, z + 0.2, x + rng.uniform(0.03, 0.08), z + 0.24, rng.uniform(0.1, 0.9))
    storage(c, rng, x0, x1, top=z0 - 0.05)


def _brick(c: Canvas, rng, x0, x1):
    region = c.region(x0, 0.0, x1, c.height_m)
    h, w = region.shape
    tone = rng.uniform(0.3, 0.6)
    detail = material(rng, ("brick",), w, h, int(rng.uniform(0.5, 0.9) * c.ppm))
    region[:] = np.clip(tone * (1.0 + 0.45 * detail), 0.02, 1.0)


PAINTERS = {
    "shelf": shelf,
    "cabinet": cabinet,
    "door": _door,
    "poster": lambda c, rng, a, b: (
        posters(c, rng, a, b, 0.25),
        _sockets(c, rng, a, b),
        low_clutter(c, rng, a, b),
    ),
    "whiteboard": lambda c, rng, a, b: (_whiteboard(c, rng, a, b), low_clutter(c, rng, a, b)),
    "window": lambda c, rng, a, b: (_window(c, rng, a, b), low_clutter(c, rng, a, b)),
    "pegboard": _pegboard,
    "lockers": lockers,
    "storage": lambda c, rng, a, b: (storage(c, rng, a, b), posters(c, rng, a, b, 1.0)),
    "brick": lambda c, rng, a, b: (_brick(c, rng, a, b), low_clutter(c, rng, a, b)),
    "plain": lambda c, rng, a, b: None,
}


def _sockets(c: Canvas, rng, x0, x1):
    if rng.random() < 0.7:
        socket(c, rng.uniform(x0, max(x0, x1 - 0.1)), 0.3)
    if rng.random() < 0.3:
        radiator(c, rng, x0 + 0.1, min(x1 - 0.1, x0 + rng.uniform(0.6, 1.4)))


def wall(spec: TextureSpec, rng: np.random.Generator) -> TextureLayers:
    """A wall or a furniture front (see the module docstring for ``params``)."""
    w, h = spec.width_px, spec.height_px
    ppm = float(spec.param("ppm"))
    img = _paint(rng, w, h, ppm, float(spec.param("paint", 0.7)))
    c = Canvas(img, ppm)
    for style, x0, x1 in spec.param("sections", ()):
        if x1 - x0 < 0.8 and style in ("whiteboard", "window", "pegboard", "door"):
            style = "poster"  # too narrow for its furniture
        PAINTERS[style](c, np.random.default_rng([spec.seed, int(x0 * 1000)]), x0, x1)
    if spec.param("skirting", True):
        tone = float(spec.param("skirting_tone", 0.9))
        plain = {s for s, _, _ in spec.param("sections", ())} == {"plain"}
        for style, x0, x1 in spec.param("sections", ()):
            if style not in ("shelf", "cabinet", "lockers", "storage", "door", "brick"):
                c.rect(x0, 0.0, x1, 0.08, tone)
                c.rect(x0, 0.08, x1, 0.085, tone * 0.75)
        if not plain:  # scuffs near the floor
            low = c.region(0.0, 0.0, c.width_m, 0.3)
            low *= 1.0 - 0.04 * np.clip(smooth_noise(rng, low.shape[1], low.shape[0], 20), 0, 3)
    return TextureLayers(albedo=to_uint8(img))

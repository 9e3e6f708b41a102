"""Painters of furniture-like units on an indoor canvas: shelves full of books, binders
and boxes, cabinets, lockers, stacked storage bins, things on the floor against a wall,
posters, sockets and radiators. Used on walls (``monoloc.sim.indoor.wall_textures``) and on the
fronts of furniture boxes (a canvas lower than 2.2 m is a furniture front: units fill
it to the top)."""

from __future__ import annotations

import numpy as np

from monoloc.sim.indoor.canvas import Canvas, word


def _top(c: Canvas, rng, low: float, high: float) -> float:
    """Top of a unit: random on a wall, the whole canvas on a furniture front."""
    return c.height_m if c.height_m < 2.2 else float(rng.uniform(low, high))


def _books(c: Canvas, rng, x0, x1, z0, z1):
    """Books, binders and boxes standing on a shelf board from z0, under z1."""
    x = x0 + rng.uniform(0.0, 0.05)
    room = z1 - z0
    while x < x1 - 0.03:
        r = rng.random()
        if r < 0.08:  # gap
            x += rng.uniform(0.05, 0.2)
            continue
        if r < 0.6:  # book
            bw, bh = rng.uniform(0.015, 0.05), room * rng.uniform(0.55, 0.95)
            tone = rng.uniform(0.08, 0.9)
            c.rect(x, z0, min(x + bw, x1), z0 + bh, tone)
            for _ in range(int(rng.integers(0, 3))):
                zb = z0 + bh * rng.uniform(0.1, 0.9)
                c.rect(x, zb, min(x + bw, x1), zb + 0.006, 1.0 - tone)
        elif r < 0.85:  # binder with a label
            bw, bh = rng.uniform(0.05, 0.08), room * rng.uniform(0.8, 0.95)
            tone = rng.uniform(0.1, 0.7)
            c.rect(x, z0, min(x + bw, x1), z0 + bh, tone)
            c.rect(x + 0.01, z0 + bh * 0.45, min(x + bw - 0.01, x1), z0 + bh * 0.85, 0.92)
            c.text(rng, word(rng), x + 0.01, z0 + bh * 0.5, x + bw - 0.01, z0 + bh * 0.8, 0.1)
            c.rect(x + bw / 2 - 0.008, z0 + bh * 0.2, x + bw / 2 + 0.008, z0 + bh * 0.3, 0.05)
            bw += 0.003
        else:  # box with a label or a framed picture
            bw, bh = rng.uniform(0.15, 0.35), room * rng.uniform(0.4, 0.85)
            bw = min(bw, x1 - x)
            if rng.random() < 0.5:
                c.rect(x, z0, x + bw, z0 + bh, rng.uniform(0.3, 0.8))
                c.rect(x + bw * 0.2, z0 + bh * 0.5, x + bw * 0.8, z0 + bh * 0.8, 0.95)
                c.text(
                    rng, word(rng), x + bw * 0.2, z0 + bh * 0.5, x + bw * 0.8, z0 + bh * 0.8, 0.1
                )
            else:
                c.rect(x, z0, x + bw, z0 + bh, 0.15)
                c.photo(rng, x + 0.01, z0 + 0.01, x + bw - 0.01, z0 + bh - 0.01)
        x += bw + rng.uniform(0.0, 0.006)


def shelf(c: Canvas, rng, x0, x1):
    top = _top(c, rng, 1.5, 2.1)
    wood = rng.uniform(0.25, 0.8)
    c.rect(x0, 0.0, x1, top, wood * 0.45)  # back panel in shadow
    board = 0.025
    levels = [0.08]
    while levels[-1] + 0.42 < top:
        levels.append(levels[-1] + rng.uniform(0.28, 0.4))
    for za, zb in zip(levels, [*levels[1:], top], strict=False):
        _books(c, rng, x0 + 0.03, x1 - 0.03, za + board, zb - 0.02)
    for z in levels:
        c.rect(x0, z, x1, z + board, wood)
        c.rect(x0, z - 0.004, x1, z, wood * 0.5)
    c.rect(x0, 0.0, x1, 0.08, wood * 0.7)  # plinth
    c.rect(x0, 0.0, x0 + 0.03, top, wood)
    c.rect(x1 - 0.03, 0.0, x1, top, wood)
    c.rect(x0, top - 0.03, x1, top, wood)
    _on_top(c, rng, x0, x1, top)


def _on_top(c: Canvas, rng, x0, x1, top):
    """Boxes and bins stored on top of a tall unit standing against a wall."""
    if top > c.height_m - 0.3:
        return
    x = x0 + rng.uniform(0.0, 0.2)
    while x < x1 - 0.25:
        w, h = rng.uniform(0.2, 0.45), rng.uniform(0.15, 0.35)
        if x + w > x1 or rng.random() < 0.3:
            x += w
            continue
        tone = rng.uniform(0.2, 0.85)
        c.rect(x, top, x + w, top + h, tone)
        c.rect(x + w * 0.2, top + h * 0.4, x + w * 0.8, top + h * 0.75, 1.0 - tone)
        c.text(rng, word(rng), x + w * 0.2, top + h * 0.4, x + w * 0.8, top + h * 0.75, tone)
        x += w + rng.uniform(0.02, 0.2)


def cabinet(c: Canvas, rng, x0, x1):
    top = _top(c, rng, 0.72, 0.95) - (0.03 if c.height_m < 2.2 else 0.0)
    tone = rng.uniform(0.3, 0.9)
    c.rect(x0, 0.0, x1, 0.09, 0.12)  # recessed plinth
    c.rect(x0, 0.09, x1, top, tone)
    x = x0
    while x < x1 - 0.2:
        w = min(rng.uniform(0.35, 0.6), x1 - x)
        if rng.random() < 0.4:  # stack of drawers
            n = int(rng.integers(3, 5))
            dz = (top - 0.1) / n
            for i in range(n):
                z = 0.1 + i * dz
                c.outline(x + 0.005, z, x + w - 0.005, z + dz - 0.005, tone * 0.55, 0.004)
                c.rect(x + w / 2 - 0.05, z + dz * 0.6, x + w / 2 + 0.05, z + dz * 0.7, 0.2)
                if rng.random() < 0.5:
                    c.rect(x + w / 2 - 0.04, z + dz * 0.25, x + w / 2 + 0.04, z + dz * 0.45, 0.9)
                    c.text(
                        rng,
                        word(rng),
                        x + w / 2 - 0.04,
                        z + dz * 0.25,
                        x + w / 2 + 0.04,
                        z + dz * 0.45,
                        0.1,
                    )
        else:
            c.outline(x + 0.005, 0.1, x + w - 0.005, top - 0.01, tone * 0.55, 0.004)
            hx = x + (w - 0.05 if rng.random() < 0.5 else 0.03)
            c.rect(hx, top - 0.25, hx + 0.015, top - 0.1, 0.2)
        x += w
    c.rect(x0 - 0.01, top, x1 + 0.01, top + 0.03, rng.uniform(0.1, 0.9))  # worktop edge
    posters(c, rng, x0, x1, z_min=top + 0.25)


def posters(c: Canvas, rng, x0, x1, z_min=0.4):
    x = x0 + rng.uniform(0.05, 0.3)
    while x < x1 - 0.35:
        pw = min(rng.uniform(0.35, 0.9), x1 - x - 0.05)
        ph = pw * rng.uniform(0.7, 1.45)
        z = rng.uniform(z_min, max(z_min, 1.3))
        if z + ph > c.height_m - 0.1:
            ph = c.height_m - 0.1 - z
        if ph < 0.2:
            break
        frame = rng.choice([0.05, 0.9, rng.uniform(0.2, 0.7)])
        c.rect(x - 0.02, z - 0.02, x + pw + 0.02, z + ph + 0.02, frame)
        if rng.random() < 0.3:  # a poster with a title band
            c.photo(rng, x, z + ph * 0.25, x + pw, z + ph)
            c.rect(x, z, x + pw, z + ph * 0.25, rng.uniform(0.8, 0.95))
            c.text(rng, word(rng), x, z, x + pw, z + ph * 0.25, 0.1)
        else:
            c.photo(rng, x, z, x + pw, z + ph)
        x += pw + rng.uniform(0.15, 0.6)


def lockers(c: Canvas, rng, x0, x1):
    top, tone = _top(c, rng, 1.75, 1.95), rng.uniform(0.35, 0.85)
    c.rect(x0, 0.0, x1, 0.1, 0.15)
    x, n = x0, int(rng.integers(1, 60))
    while x < x1 - 0.25:
        w = min(rng.uniform(0.3, 0.4), x1 - x)
        c.rect(x + 0.005, 0.1, x + w - 0.005, top, tone)
        for z in np.arange(top - 0.2, top - 0.05, 0.025):  # vents
            c.rect(x + 0.08, z, x + w - 0.08, z + 0.01, tone * 0.4)
        c.rect(x + w * 0.35, top - 0.33, x + w * 0.65, top - 0.26, 0.92)
        c.text(rng, str(n), x + w * 0.37, top - 0.325, x + w * 0.63, top - 0.265, 0.05)
        c.rect(x + w - 0.07, 1.0, x + w - 0.04, 1.08, 0.1)
        x, n = x + w, n + 1
    _on_top(c, rng, x0, x1, top)


def storage(c: Canvas, rng, x0, x1, top=None):
    """Stacked bins and boxes along the bottom of the wall."""
    top = top if top is not None else rng.uniform(0.5, 0.9)
    x = x0 + 0.02
    while x < x1 - 0.2:
        w = min(rng.uniform(0.25, 0.55), x1 - x)
        z = 0.0
        while z < top - 0.12:
            h = min(rng.uniform(0.12, 0.3), top - z)
            tone = rng.uniform(0.15, 0.85)
            c.rect(x, z, x + w - 0.01, z + h - 0.005, tone)
            c.rect(x, z + h - 0.025, x + w - 0.01, z + h - 0.005, tone * 0.7)  # lid
            if rng.random() < 0.7:
                c.rect(x + w * 0.25, z + h * 0.35, x + w * 0.75, z + h * 0.7, 0.93)
                c.text(rng, word(rng), x + w * 0.25, z + h * 0.35, x + w * 0.75, z + h * 0.7, 0.08)
            z += h
        x += w


def low_clutter(c: Canvas, rng, x0, x1):
    """Things standing against the wall on the floor: bins, bags, boxes, a cable run."""
    x = x0 + rng.uniform(0.0, 0.3)
    while x < x1 - 0.2:
        w = min(rng.uniform(0.15, 0.5), x1 - x)
        h = rng.uniform(0.1, 0.5)
        tone = rng.uniform(0.05, 0.9)
        r = rng.random()
        if r < 0.35:  # bin with a rim and a label
            c.rect(x, 0.0, x + w, h, tone)
            c.rect(x - 0.01, h - 0.03, x + w + 0.01, h, tone * 0.6 + 0.2)
            c.rect(x + w * 0.2, h * 0.4, x + w * 0.8, h * 0.7, 1.0 - tone)
            c.text(rng, word(rng), x + w * 0.2, h * 0.4, x + w * 0.8, h * 0.7, tone)
        elif r < 0.6:  # bag or case: a photo-textured lump
            c.photo(rng, x, 0.0, x + w, h, 0.05, 0.7)
        elif r < 0.8:  # box with tape and print
            c.rect(x, 0.0, x + w, h, rng.uniform(0.45, 0.65))
            c.rect(x, h * 0.45, x + w, h * 0.55, 0.75)
            c.text(rng, word(rng), x + 0.02, h * 0.6, x + w - 0.02, h * 0.9, 0.1)
        else:  # power strip with plugs and cables up to a socket
            c.rect(x, 0.02, x + 0.35, 0.07, 0.92)
            for k in range(4):
                c.rect(x + 0.03 + k * 0.08, 0.03, x + 0.07 + k * 0.08, 0.08, 0.08)
                c.rect(x + 0.045 + k * 0.08, 0.08, x + 0.052 + k * 0.08, rng.uniform(0.1, 0.4), 0.1)
            w = 0.35
        x += w + rng.uniform(0.02, 0.35)


def socket(c: Canvas, x, z, tone=0.9):
    c.rect(x, z, x + 0.08, z + 0.08, tone)
    c.outline(x, z, x + 0.08, z + 0.08, tone * 0.6, 0.004)
    for dx in (0.025, 0.047):
        c.rect(x + dx, z + 0.035, x + dx + 0.008, z + 0.045, 0.15)


def radiator(c: Canvas, rng, x0, x1, z0=0.12, z1=None):
    z1 = z1 or rng.uniform(0.5, 0.7)
    tone = rng.uniform(0.75, 0.92)
    c.rect(x0, z0, x1, z1, tone)
    fin = rng.uniform(0.03, 0.05)
    x = x0 + fin / 2
    while x < x1 - 0.01:
        c.rect(x, z0 + 0.02, x + 0.006, z1 - 0.02, tone * 0.7)
        x += fin
    c.rect(x1 - 0.04, z0 - 0.05, x1 - 0.02, z0, 0.4)  # pipe
    c.rect(x1 - 0.01, z0 + 0.05, x1 + 0.02, z0 + 0.09, 0.3)  # valve

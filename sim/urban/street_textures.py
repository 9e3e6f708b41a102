"""Texture generators for the street: asphalt, markings, paving, kerbs, vegetation,
cars, poles, lamps and signs. Deterministic in ``spec.seed``; values are albedo in
[0, 1] before conversion to uint8 (``monoloc.sim.texture_tools``)."""

from __future__ import annotations

import numpy as np

from monoloc.sim.texture_tools import (
    PICTURE_PHOTOS,
    SHOP_WORDS,
    crop_resize,
    material,
    photo_gray,
    put_text_fit,
    smooth_noise,
    to_uint8,
)
from monoloc.sim.textures import TextureLayers, TextureSpec


def _asphalt(rng, w, h, ppm) -> np.ndarray:
    tone = rng.uniform(0.22, 0.34)
    grain = material(rng, ("gravel",), w, h, int(rng.uniform(1.5, 3.0) * ppm))
    img = tone * (1.0 + 0.12 * grain + 0.10 * smooth_noise(rng, w, h, 3 * ppm))
    img += 0.015 * rng.standard_normal((h, w)).astype(np.float32)
    return img.astype(np.float32)


def _cracks_and_patches(img, rng, ppm, count):
    import cv2

    h, w = img.shape
    for _ in range(count):
        if rng.random() < 0.5:  # repaired patch
            pw, ph = rng.uniform(0.5, 3) * ppm, rng.uniform(0.5, 2) * ppm
            x, y = rng.uniform(0, w), rng.uniform(0, h)
            pts = np.array(
                [
                    [x, y],
                    [x + pw, y + rng.normal(0, 3)],
                    [x + pw, y + ph],
                    [x + rng.normal(0, 3), y + ph],
                ],
                np.int32,
            )
            patch = img.copy()
            cv2.fillConvexPoly(patch, pts, float(img.mean() * rng.uniform(0.75, 1.2)))
            img[:] = 0.3 * img + 0.7 * patch if rng.random() < 0.5 else patch * 0.5 + img * 0.5
        else:  # crack: a random walk
            p = np.array([rng.uniform(0, w), rng.uniform(0, h)])
            angle = rng.uniform(0, 2 * np.pi)
            pts = [p.copy()]
            for _ in range(int(rng.integers(5, 25))):
                angle += rng.normal(0, 0.5)
                p = p + 0.15 * ppm * np.array([np.cos(angle), np.sin(angle)])
                pts.append(p.copy())
            cv2.polylines(
                img, [np.array(pts, np.int32)], False, float(img.mean() * 0.45), 1, cv2.LINE_AA
            )


def _manhole(img, rng, x, y, ppm):
    import cv2

    r = int(0.32 * ppm)
    cv2.circle(img, (int(x), int(y)), r, float(rng.uniform(0.12, 0.22)), -1, cv2.LINE_AA)
    for k in range(-r, r, max(2, int(0.08 * ppm))):
        cv2.line(img, (int(x - r), int(y + k)), (int(x + r), int(y + k)), 0.3, 1)
    cv2.circle(img, (int(x), int(y)), r, 0.35, max(1, int(0.04 * ppm)), cv2.LINE_AA)
    cv2.circle(img, (int(x), int(y)), r + 1, float(img.mean()), 1)


def road(spec: TextureSpec, rng: np.random.Generator) -> TextureLayers:
    """A street segment: x along the street (length_m), y across (width_m, driving lanes
    split by a dashed centre line); optional crosswalks at either end."""
    import cv2

    w, h = spec.width_px, spec.height_px
    ppm = float(spec.param("ppm"))
    img = _asphalt(rng, w, h, ppm)
    # Darker wheel tracks in each lane.
    yy = np.arange(h, dtype=np.float32) / ppm
    width_m = h / ppm
    for lane_centre in (width_m * 0.25, width_m * 0.75):
        for off in (-0.8, 0.8):
            img *= (1.0 - 0.06 * np.exp(-(((yy - lane_centre - off) / 0.35) ** 2)))[:, None]
    _cracks_and_patches(img, rng, ppm, int(w / ppm / 6) + 1)
    for _ in range(int(rng.integers(0, 2 + w // int(25 * ppm)))):
        _manhole(img, rng, rng.uniform(0.1, 0.9) * w, rng.uniform(0.2, 0.8) * h, ppm)
    paint = rng.uniform(0.65, 0.85)
    wear = 1.0 - 0.35 * np.clip(smooth_noise(rng, w, h, 0.3 * ppm), 0, None)
    marks = np.zeros((h, w), np.float32)
    lw = max(2, int(0.13 * ppm))
    cy = h // 2
    dash, gap = rng.uniform(2.5, 4.0) * ppm, rng.uniform(3.0, 6.0) * ppm
    phase = rng.uniform(0, dash + gap)
    x = -phase
    x_lo = 6 * ppm if spec.param("cross_start") else 0
    x_hi = w - 6 * ppm if spec.param("cross_end") else w
    while x < w:
        a, b = max(x, x_lo), min(x + dash, x_hi)
        if b > a:
            cv2.rectangle(marks, (int(a), cy - lw // 2), (int(b), cy + lw // 2), 1.0, -1)
        x += dash + gap
    if spec.param("edge_lines"):
        e = int(0.3 * ppm)
        marks[e : e + lw, :] = 1.0
        marks[h - e - lw : h - e, :] = 1.0
    for end, flag in ((0, spec.param("cross_start")), (1, spec.param("cross_end"))):
        if not flag:
            continue
        stripe = int(0.5 * ppm)
        x0 = int(0.3 * ppm) if end == 0 else int(w - 4.3 * ppm)
        for y in range(int(0.3 * ppm), h - stripe, 2 * stripe):
            cv2.rectangle(marks, (x0, y), (x0 + int(4 * ppm), y + stripe), 1.0, -1)
        sx = int(4.8 * ppm) if end == 0 else int(w - 5.2 * ppm)
        ys = (cy, h) if end == 0 else (0, cy)
        cv2.rectangle(marks, (sx, ys[0]), (sx + int(0.35 * ppm), ys[1] - 1), 1.0, -1)
    img = img * (1 - marks * wear) + paint * marks * wear
    return TextureLayers(albedo=to_uint8(img))


def asphalt(spec: TextureSpec, rng: np.random.Generator) -> TextureLayers:
    """Plain asphalt (intersections, the base ground under everything)."""
    ppm = float(spec.param("ppm"))
    img = _asphalt(rng, spec.width_px, spec.height_px, ppm)
    if not spec.wrap:
        _cracks_and_patches(img, rng, ppm, 3)
    return TextureLayers(albedo=to_uint8(img))


def sidewalk(spec: TextureSpec, rng: np.random.Generator) -> TextureLayers:
    """Paving slabs of random size per sidewalk, each slab a slightly different tone."""
    w, h = spec.width_px, spec.height_px
    ppm = float(spec.param("ppm"))
    tone = rng.uniform(0.4, 0.6)
    grain = material(rng, ("gravel", "moon", "brick"), w, h, int(rng.uniform(1, 2) * ppm))
    img = tone * (1.0 + 0.06 * grain + 0.07 * smooth_noise(rng, w, h, 2 * ppm))
    slab_w, slab_h = rng.uniform(0.3, 0.8) * ppm, rng.uniform(0.3, 0.8) * ppm
    yy, xx = np.mgrid[0:h, 0:w]
    cell = (xx // slab_w).astype(np.int64) * 7919 + (yy // slab_h).astype(np.int64)
    jitter = rng.standard_normal(int(cell.max()) + 1).astype(np.float32)
    img *= 1.0 + 0.05 * jitter[cell]
    joints = ((xx % slab_w) < 1.5) | ((yy % slab_h) < 1.5)
    img[joints] *= 0.6
    _cracks_and_patches(img, rng, ppm, int(w / ppm / 15))
    return TextureLayers(albedo=to_uint8(img))


def kerb(spec: TextureSpec, rng: np.random.Generator) -> TextureLayers:
    """Concrete kerb stones, joints about every metre."""
    w, h = spec.width_px, spec.height_px
    ppm = float(spec.param("ppm"))
    img = rng.uniform(0.5, 0.7) * (1 + 0.05 * smooth_noise(rng, w, h, ppm))
    img = np.broadcast_to(img, (h, w)).copy()
    for x in np.arange(rng.uniform(0, ppm), w, rng.uniform(0.8, 1.2) * ppm):
        img[:, int(x) : int(x) + 2] *= 0.6
    img[-max(1, h // 4) :, :] *= 0.7
    return TextureLayers(albedo=to_uint8(img))


def lawn(spec: TextureSpec, rng: np.random.Generator) -> TextureLayers:
    """Grass or gravel patches (block interiors, verges)."""
    w, h = spec.width_px, spec.height_px
    ppm = float(spec.param("ppm"))
    names = ("grass",) if rng.random() < 0.7 else ("gravel",)
    img = rng.uniform(0.25, 0.45) * (
        1
        + 0.25 * material(rng, names, w, h, int(2 * ppm))
        + 0.15 * smooth_noise(rng, w, h, 3 * ppm)
    )
    return TextureLayers(albedo=to_uint8(img))


def car(spec: TextureSpec, rng: np.random.Generator) -> TextureLayers:
    """One face of a parked car; params face (side|front|back|top|cabin_side|cabin_end),
    body tone shared by the faces of one car (param tone)."""
    import cv2

    w, h = spec.width_px, spec.height_px
    ppm = float(spec.param("ppm"))
    tone = float(spec.param("tone"))
    face = spec.param("face")
    img = np.full((h, w), tone, np.float32)
    img *= 1.0 + 0.04 * smooth_noise(rng, w, h, ppm)
    img += np.linspace(0.08, -0.06, h, dtype=np.float32)[:, None]  # sky reflection
    if face == "side":
        for fx in (0.18, 0.82):  # wheels
            c = (int(fx * w), int(h - 0.08 * ppm))
            cv2.circle(img, c, int(0.33 * ppm), 0.05, -1, cv2.LINE_AA)
            cv2.circle(img, c, int(0.2 * ppm), float(rng.uniform(0.4, 0.7)), -1, cv2.LINE_AA)
            cv2.circle(img, c, int(0.06 * ppm), 0.15, -1)
        for fx in (0.3, 0.55):  # door seams, handles
            cv2.line(img, (int(fx * w), 0), (int(fx * w), int(h * 0.8)), tone * 0.5, 1)
            cv2.rectangle(
                img,
                (int(fx * w + 0.1 * ppm), int(0.25 * h)),
                (int(fx * w + 0.3 * ppm), int(0.25 * h + 0.05 * ppm)),
                tone * 0.6,
                -1,
            )
        img[int(0.85 * h) :, :] *= 0.4
    elif face in ("front", "back"):
        light = 0.9 if face == "front" else 0.35
        for fx in (0.08, 0.72):
            cv2.rectangle(
                img, (int(fx * w), int(0.2 * h)), (int((fx + 0.2) * w), int(0.4 * h)), light, -1
            )
        cv2.rectangle(img, (int(0.38 * w), int(0.5 * h)), (int(0.62 * w), int(0.68 * h)), 0.92, -1)
        plate = f"{SHOP_WORDS[int(rng.integers(len(SHOP_WORDS)))][:2]} {rng.integers(10, 9999)}"
        put_text_fit(
            img, plate, int(0.38 * w), int(0.5 * h), int(0.24 * w), int(0.18 * h), 0.05, rng
        )
        if face == "front":
            cv2.rectangle(img, (int(0.3 * w), int(0.2 * h)), (int(0.7 * w), int(0.4 * h)), 0.1, -1)
        img[int(0.85 * h) :, :] *= 0.4
    elif face in ("cabin_side", "cabin_end"):
        glass = crop_resize(rng, photo_gray(rng, PICTURE_PHOTOS), w, h)
        m = max(1, int(0.06 * ppm))
        img[m:, m:-m] = 0.06 + 0.2 * glass[m:, m:-m]
        if face == "cabin_side":
            img[:, w // 2 - m : w // 2 + m] = tone
    emission = None
    if face == "front" and spec.param("lit"):
        emission = np.zeros((h, w), np.uint8)
    return TextureLayers(albedo=to_uint8(img), emission=emission)


def metal(spec: TextureSpec, rng: np.random.Generator) -> TextureLayers:
    """Poles, posts and trunks: a tone with streaks (param bark for tree trunks), stickers."""
    w, h = spec.width_px, spec.height_px
    ppm = float(spec.param("ppm"))
    if spec.param("bark"):
        img = rng.uniform(0.2, 0.35) * (
            1 + 0.35 * material(rng, ("gravel", "brick"), w, h, int(0.8 * ppm))
        )
    else:
        img = rng.uniform(0.25, 0.6) * (1 + 0.08 * smooth_noise(rng, w, h, 0.5 * ppm))
        img = np.broadcast_to(img, (h, w)).copy()
        for _ in range(int(rng.integers(0, 3))):  # stickers
            sh = int(rng.uniform(0.1, 0.3) * ppm)
            y = int(rng.uniform(0.3, 0.8) * h)
            img[y : y + sh, :] = (
                0.1 + 0.8 * crop_resize(rng, photo_gray(rng, PICTURE_PHOTOS), w, sh)[: h - y]
            )
    return TextureLayers(albedo=to_uint8(img))


def lamp(spec: TextureSpec, rng: np.random.Generator) -> TextureLayers:
    """A street-lamp head: dark housing, glowing at night."""
    w, h = spec.width_px, spec.height_px
    img = np.full((h, w), rng.uniform(0.2, 0.4), np.float32)
    emission = np.full((h, w), 1.0, np.float32)
    return TextureLayers(albedo=to_uint8(img), emission=to_uint8(emission))


def sign(spec: TextureSpec, rng: np.random.Generator) -> TextureLayers:
    """A road or shop sign: a shape with a border and a word or a symbol, alpha outside."""
    import cv2

    w, h = spec.width_px, spec.height_px
    img = np.full((h, w), rng.uniform(0.7, 0.95), np.float32)
    alpha = np.zeros((h, w), np.float32)
    shape = rng.choice(["circle", "rect", "triangle"])
    border = max(2, w // 10)
    if shape == "circle":
        cv2.circle(alpha, (w // 2, h // 2), min(w, h) // 2 - 1, 1.0, -1)
        cv2.circle(img, (w // 2, h // 2), min(w, h) // 2 - 1, 0.25, border)
    elif shape == "triangle":
        pts = np.array([[w // 2, 1], [w - 2, h - 2], [1, h - 2]], np.int32)
        cv2.fillConvexPoly(alpha, pts, 1.0)
        cv2.polylines(img, [pts], True, 0.25, border)
    else:
        alpha[:] = 1.0
        cv2.rectangle(img, (0, 0), (w - 1, h - 1), 0.15, border)
    word = (
        SHOP_WORDS[int(rng.integers(len(SHOP_WORDS)))]
        if rng.random() < 0.5
        else str(int(rng.integers(10, 80)))
    )
    put_text_fit(img, word, w // 5, h // 3, 3 * w // 5, h // 3, 0.05, rng)
    return TextureLayers(albedo=to_uint8(img), alpha=to_uint8(alpha))


def foliage(spec: TextureSpec, rng: np.random.Generator) -> TextureLayers:
    """A tree crown billboard: leaves from the grass photo, alpha a ragged blob."""
    import cv2

    w, h = spec.width_px, spec.height_px
    ppm = float(spec.param("ppm"))
    leaves = rng.uniform(0.15, 0.3) * (
        1
        + 0.5 * material(rng, ("grass",), w, h, int(ppm))
        + 0.3 * smooth_noise(rng, w, h, 0.4 * ppm)
    )
    blob = np.zeros((h, w), np.float32)
    for _ in range(12):
        cx, cy = rng.normal(w / 2, w / 7), rng.normal(h / 2, h / 7)
        r = rng.uniform(0.15, 0.3) * min(w, h)
        cv2.circle(blob, (int(cx), int(cy)), int(r), 1.0, -1)
    ragged = blob * (0.6 + 0.4 * smooth_noise(rng, w, h, 0.15 * ppm)) > 0.45
    return TextureLayers(albedo=to_uint8(leaves), alpha=to_uint8(ragged.astype(np.float32)))

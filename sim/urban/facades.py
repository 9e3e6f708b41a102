"""Facade textures of the city's buildings (kind ``facade``).

Facades are built from real photographs (scikit-image samples) cropped, tiled and
recoloured, with procedural windows, doors, shop signs with text, posters, grime and
some plain walls. Deterministic in ``spec.seed``; values are albedo in [0, 1] before
conversion to uint8.
"""

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


def _wall_base(rng, w, h, ppm, plain: bool) -> np.ndarray:
    """Wall material: tone + photo-derived detail + low-frequency weathering."""
    tone = rng.uniform(0.3, 0.75)
    if plain:
        # A featureless wall: smooth paint, very gentle gradients only.
        return (tone * (1.0 + 0.03 * smooth_noise(rng, w, h, 8 * ppm))).astype(np.float32)
    kind = rng.choice(
        ["brick", "plaster", "stone", "panels", "siding"], p=[0.3, 0.3, 0.15, 0.15, 0.1]
    )
    if kind == "brick":
        detail = material(rng, ("brick",), w, h, int(rng.uniform(2.0, 3.5) * ppm)) * 0.09
    elif kind == "stone":
        detail = material(rng, ("gravel", "moon", "cell"), w, h, int(rng.uniform(2, 5) * ppm))
        detail *= 0.07
    elif kind == "plaster":
        detail = material(rng, ("gravel", "moon"), w, h, int(rng.uniform(1.0, 2.5) * ppm))
        detail *= 0.035
    elif kind == "panels":
        detail = material(rng, ("gravel", "moon"), w, h, int(1.5 * ppm)) * 0.025
        pw, ph = rng.uniform(1.2, 3.0) * ppm, rng.uniform(1.0, 3.5) * ppm
        yy, xx = np.mgrid[0:h, 0:w]
        cell = (xx // pw).astype(np.int64) * 131 + (yy // ph).astype(np.int64)
        detail += ((cell * 2654435761 % 1000) / 1000.0 - 0.5).astype(np.float32) * 0.08
        joints = ((xx % pw) < 2) | ((yy % ph) < 2)
        detail[joints] -= 0.25
    else:  # siding: horizontal boards
        detail = material(rng, ("gravel",), w, h, int(2 * ppm)) * 0.03
        board = max(3, int(rng.uniform(0.12, 0.25) * ppm))
        rows = np.arange(h) % board
        detail += np.where(rows < 2, -0.15, 0.02 * np.sin(rows / board * np.pi))[:, None]
    weathering = 1.0 + 0.08 * smooth_noise(rng, w, h, rng.uniform(2, 6) * ppm)
    return (tone * weathering + detail * tone).astype(np.float32)


def _glass(rng, w, h, interior: bool) -> tuple[np.ndarray, np.ndarray]:
    """A window pane (albedo, night emission) of (h, w): dark glass reflecting or showing a
    random photo crop, or lit curtains."""
    photo = crop_resize(rng, photo_gray(rng, PICTURE_PHOTOS), w, h, min_fraction=0.15)
    base = rng.uniform(0.05, 0.2)
    contrast = rng.uniform(0.25, 0.6) if interior else rng.uniform(0.1, 0.35)
    pane = base + contrast * photo
    pane += np.linspace(0.06, -0.03, h, dtype=np.float32)[:, None]
    curtain = rng.random() < 0.35
    if curtain:
        folds = 0.5 + 0.5 * np.sin(np.arange(w) / max(2.0, rng.uniform(2, 6)))
        pane = rng.uniform(0.45, 0.8) * (0.85 + 0.15 * folds)[None, :] + 0.05 * photo
        pane = np.repeat(pane[:1], h, axis=0) if pane.shape[0] == 1 else pane
    emission = np.zeros((h, w), np.float32)
    if rng.random() < 0.35:  # lit at night
        emission[:] = rng.uniform(0.35, 0.9) * (0.7 + 0.3 * photo)
    return pane.astype(np.float32), emission


def _draw_window(img, emis, rng, x, y, w, h, frame_tone, ppm, interior=False, bars=True):
    import cv2

    x, y, w, h = int(x), int(y), int(w), int(h)
    if w < 4 or h < 4 or x < 0 or y < 0 or x + w > img.shape[1] or y + h > img.shape[0]:
        return
    f = max(1, int(0.07 * ppm))
    cv2.rectangle(img, (x - f, y - f), (x + w + f - 1, y + h + f - 1), float(frame_tone), -1)
    pane, light = _glass(rng, w, h, interior)
    img[y : y + h, x : x + w] = pane
    emis[y : y + h, x : x + w] = light
    if bars and w > 6 * f:
        cv2.rectangle(
            img, (x + w // 2 - f // 2, y), (x + w // 2 + f // 2, y + h - 1), float(frame_tone), -1
        )
        if rng.random() < 0.6:
            ty = y + int(h * rng.uniform(0.25, 0.4))
            cv2.rectangle(img, (x, ty), (x + w - 1, ty + f), float(frame_tone), -1)
    sill = max(2, int(0.08 * ppm))
    cv2.rectangle(
        img,
        (x - 2 * f, y + h + f),
        (x + w + 2 * f, y + h + f + sill),
        float(min(1.0, frame_tone * 1.1 + 0.1)),
        -1,
    )


def facade(spec: TextureSpec, rng: np.random.Generator) -> TextureLayers:
    """A building facade; params width_m, height_m, ppm, style (plain|windows|shops)."""
    import cv2

    w, h = spec.width_px, spec.height_px
    ppm = float(spec.param("ppm"))
    style = spec.param("style", "windows")
    img = _wall_base(rng, w, h, ppm, plain=(style == "plain"))
    emis = np.zeros((h, w), np.float32)
    if style != "plain":
        frame_tone = rng.choice([rng.uniform(0.75, 0.95), rng.uniform(0.1, 0.3)])
        floor_h = rng.uniform(2.9, 3.6) * ppm
        ground_h = (rng.uniform(3.6, 4.6) if style == "shops" else floor_h / ppm) * ppm
        win_w = rng.uniform(0.9, 1.6) * ppm
        win_h = rng.uniform(1.3, 1.9) * ppm
        spacing = max(win_w + 0.6 * ppm, rng.uniform(2.2, 3.8) * ppm)
        n_cols = max(1, int((w - 0.8 * ppm) / spacing))
        margin = (w - n_cols * spacing) / 2
        band = rng.random() < 0.6
        # Upper floors: a grid of windows (repeated-looking, but each pane differs).
        top = h - ground_h
        row = 0
        while top - floor_h * (row + 1) > -0.3 * ppm:
            fy = top - floor_h * (row + 1)
            wy = fy + floor_h - 0.9 * ppm - win_h
            if band:
                cv2.rectangle(
                    img,
                    (0, int(fy + floor_h - 0.12 * ppm)),
                    (w - 1, int(fy + floor_h)),
                    float(img.mean() * rng.uniform(0.8, 1.25)),
                    -1,
                )
            for c in range(n_cols):
                if rng.random() < 0.04:
                    continue  # a bricked-up window breaks the pattern
                wx = margin + c * spacing + (spacing - win_w) / 2
                _draw_window(img, emis, rng, wx, wy, win_w, win_h, frame_tone, ppm)
            row += 1
        _ground_floor(
            img, emis, rng, w, h, ground_h, ppm, style, spacing, margin, n_cols, win_w, frame_tone
        )
        if rng.random() < 0.5:  # drainpipe
            px = int(rng.choice([0.15 * ppm, w - 0.3 * ppm]))
            cv2.rectangle(
                img, (px, 0), (px + max(2, int(0.1 * ppm)), h - 1), float(rng.uniform(0.2, 0.5)), -1
            )
    # Grime: darker near the ground, streaks, overall weathering.
    yy = np.arange(h, dtype=np.float32)[:, None]
    img *= 1.0 - 0.25 * np.exp(-(h - yy) / (0.5 * ppm))
    if rng.random() < 0.5:
        img *= 1.0 + 0.06 * smooth_noise(rng, w, h, 0.7 * ppm)
    return TextureLayers(albedo=to_uint8(img), emission=to_uint8(emis) if emis.any() else None)


def _ground_floor(
    img, emis, rng, w, h, ground_h, ppm, style, spacing, margin, n_cols, win_w, frame_tone
):
    import cv2

    y_floor = h - 1
    y_top = h - ground_h
    door_w, door_h = rng.uniform(1.0, 1.8) * ppm, rng.uniform(2.1, 2.5) * ppm
    door_col = int(rng.integers(n_cols))
    if style == "shops":
        # Shop fronts: wide display windows, a door, a sign board with a word.
        sign_h = rng.uniform(0.5, 0.9) * ppm
        sign_tone = rng.choice([rng.uniform(0.05, 0.25), rng.uniform(0.7, 0.95)])
        x = 0.3 * ppm
        while x < w - 1.5 * ppm:
            shop_w = min(w - x - 0.3 * ppm, rng.uniform(4.0, 9.0) * ppm)
            sy = int(y_top + 0.25 * ppm)
            cv2.rectangle(
                img, (int(x), sy), (int(x + shop_w), int(sy + sign_h)), float(sign_tone), -1
            )
            word = SHOP_WORDS[int(rng.integers(len(SHOP_WORDS)))]
            if rng.random() < 0.3:
                word += f" {int(rng.integers(1, 99))}"
            put_text_fit(
                img,
                word,
                int(x),
                sy,
                int(shop_w),
                int(sign_h),
                1.0 - sign_tone if rng.random() < 0.8 else 0.5,
                rng,
            )
            wy = sy + sign_h + 0.3 * ppm
            wh = y_floor - 0.5 * ppm - wy
            dx = x + rng.uniform(0.2, 0.5) * ppm
            dw = door_w if shop_w > 3 * ppm else 0
            _draw_window(
                img,
                emis,
                rng,
                dx + dw + 0.3 * ppm,
                wy,
                shop_w - dw - 0.8 * ppm,
                wh,
                frame_tone,
                ppm,
                interior=True,
                bars=rng.random() < 0.4,
            )
            if dw:
                _door(img, rng, dx, y_floor - door_h, dw, door_h, ppm)
            x += shop_w + rng.uniform(0.3, 1.5) * ppm
    else:
        wy = y_top + (ground_h - 0.9 * ppm - rng.uniform(1.3, 1.8) * ppm)
        for c in range(n_cols):
            cx = margin + c * spacing + spacing / 2
            if c == door_col:
                _door(img, rng, cx - door_w / 2, y_floor - door_h, door_w, door_h, ppm)
            elif rng.random() < 0.8:
                _draw_window(
                    img,
                    emis,
                    rng,
                    cx - win_w / 2,
                    wy,
                    win_w,
                    y_floor - 0.9 * ppm - wy,
                    frame_tone,
                    ppm,
                )
    # Posters and house numbers: unique, high-contrast details at eye level.
    for _ in range(int(rng.integers(0, 3))):
        pw, ph = rng.uniform(0.5, 1.2) * ppm, rng.uniform(0.7, 1.5) * ppm
        px, py = rng.uniform(0, max(1, w - pw)), y_floor - rng.uniform(1.0, 2.2) * ppm - ph
        if py < 0:
            continue
        poster = crop_resize(rng, photo_gray(rng, PICTURE_PHOTOS), pw, ph)
        img[int(py) : int(py) + poster.shape[0], int(px) : int(px) + poster.shape[1]] = (
            0.1 + 0.8 * poster
        )[: h - int(py), : w - int(px)]


def _door(img, rng, x, y, w, h, ppm):
    import cv2

    x, y, w, h = int(x), int(y), int(w), int(h)
    tone = rng.uniform(0.05, 0.5)
    cv2.rectangle(img, (x, y), (x + w, y + h), float(tone), -1)
    f = max(1, int(0.08 * ppm))
    cv2.rectangle(
        img,
        (x + 2 * f, y + 2 * f),
        (x + w - 2 * f, y + h // 2 - f),
        float(tone * 0.7 + 0.1),
        max(1, f // 2),
    )
    cv2.rectangle(
        img,
        (x + 2 * f, y + h // 2 + f),
        (x + w - 2 * f, y + h - 2 * f),
        float(tone * 0.7 + 0.1),
        max(1, f // 2),
    )
    cv2.circle(img, (x + w - 3 * f, y + h // 2), max(1, f), float(0.9 - tone), -1)
    if rng.random() < 0.5:
        put_text_fit(
            img,
            str(int(rng.integers(1, 200))),
            x,
            y - int(0.45 * ppm),
            w,
            int(0.35 * ppm),
            0.9 if tone < 0.4 else 0.1,
            rng,
        )

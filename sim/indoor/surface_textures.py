"""Indoor surface textures besides walls and floor: the suspended ceiling
(``indoor_ceiling``), its light panels (``indoor_lamp``) and the sides and tops of
furniture and boxes (``indoor_surface``)."""

from __future__ import annotations

import numpy as np

from monoloc.sim.indoor.canvas import Canvas, word
from monoloc.sim.texture_tools import material, smooth_noise, to_uint8
from monoloc.sim.textures import TextureLayers, TextureSpec


def ceiling(spec: TextureSpec, rng: np.random.Generator) -> TextureLayers:
    """Suspended ceiling: 0.6 m tiles, speckle, light panels. params: ppm, x_min, y_min,
    lights ((x, y), ...) world positions (texture x along +x, y along +y)."""
    w, h = spec.width_px, spec.height_px
    ppm = float(spec.param("ppm"))
    img = 0.85 * (1.0 + 0.04 * material(rng, ("gravel", "moon"), w, h, int(0.3 * ppm)))
    grid = int(0.6 * ppm)
    img[:: max(grid, 1), :] = 0.6
    img[:, :: max(grid, 1)] = 0.6
    x_min, y_min = float(spec.param("x_min")), float(spec.param("y_min"))
    for x, y in spec.param("lights", ()):
        c0, r0 = int((x - x_min - 0.3) * ppm), int((y - y_min - 0.3) * ppm)
        img[max(r0, 0) : max(r0 + grid, 0), max(c0, 0) : max(c0 + grid, 0)] = 1.0
    return TextureLayers(albedo=to_uint8(img.astype(np.float32)))


def lamp_panel(spec: TextureSpec, rng: np.random.Generator) -> TextureLayers:
    """A ceiling light panel: a frame and a louvre grid around glowing diffusers (the
    emission layer makes it shine when the lighting has ``window_glow``)."""
    w, h = spec.width_px, spec.height_px
    img = np.full((h, w), 0.9, np.float32)
    emission = np.full((h, w), 1.0, np.float32)
    frame = max(1, w // 20)
    for arr, value in ((img, 0.55), (emission, 0.0)):
        arr[:frame], arr[-frame:], arr[:, :frame], arr[:, -frame:] = value, value, value, value
        arr[:, w // 2 - frame // 2 : w // 2 + frame // 2 + 1] = value
        arr[h // 3 : h // 3 + frame], arr[2 * h // 3 : 2 * h // 3 + frame] = value, value
    return TextureLayers(albedo=to_uint8(img), emission=to_uint8(emission))


def surface(spec: TextureSpec, rng: np.random.Generator) -> TextureLayers:
    """Furniture sides and tops, and the bare end's floor mat. params: ppm, style
    (wood|cardboard|metal|foam|mat)."""
    import cv2

    w, h = spec.width_px, spec.height_px
    ppm = float(spec.param("ppm"))
    style = spec.param("style", "wood")
    if style == "wood":
        grain = cv2.resize(
            rng.standard_normal((max(2, h // 3), max(2, w // 60))).astype(np.float32),
            (w, h),
            interpolation=cv2.INTER_CUBIC,
        )
        img = rng.uniform(0.3, 0.75) * (1.0 + 0.06 * grain)
    elif style == "metal":
        brushed = cv2.resize(
            rng.standard_normal((h, max(2, w // 30))).astype(np.float32),
            (w, h),
            interpolation=cv2.INTER_LINEAR,
        )
        img = rng.uniform(0.4, 0.8) * (1.0 + 0.03 * brushed)
    elif style == "mat":  # plain rubber: a faint, smooth unevenness, nothing to match
        img = rng.uniform(0.35, 0.45) * (1.0 + 0.01 * smooth_noise(rng, w, h, 0.5 * ppm))
    elif style == "foam":
        img = rng.uniform(0.15, 0.85) * (1.0 + 0.05 * material(rng, ("moon",), w, h, 30))
    else:  # cardboard with tape, print, a shipping label
        tone = rng.uniform(0.5, 0.68)
        img = tone * (1.0 + 0.03 * smooth_noise(rng, w, h, 0.1 * ppm))
        img = img.astype(np.float32)
        c = Canvas(img, ppm)
        band = rng.uniform(0.04, 0.06)
        c.rect(0, c.height_m / 2 - band / 2, c.width_m, c.height_m / 2 + band / 2, tone * 1.25)
        bw, bh = min(0.3, c.width_m * 0.7), min(0.12, c.height_m * 0.25)
        c.text(rng, word(rng), 0.05, c.height_m - 0.05 - bh, 0.05 + bw, c.height_m - 0.05, 0.1)
        if c.width_m > 0.25 and c.height_m > 0.2 and rng.random() < 0.6:  # shipping label
            x0, z0 = rng.uniform(0.03, c.width_m - 0.17), rng.uniform(0.03, 0.08)
            c.rect(x0, z0, x0 + 0.14, z0 + 0.1, 0.92)
            c.text(rng, word(rng), x0 + 0.01, z0 + 0.065, x0 + 0.13, z0 + 0.09, 0.1)
            x = x0 + 0.01
            while x < x0 + 0.12:  # barcode, bars no finer than the texture resolves
                bar = float(rng.choice([0.007, 0.014]))
                c.rect(x, z0 + 0.01, x + bar, z0 + 0.055, 0.08)
                x += bar + float(rng.choice([0.007, 0.014]))
        if rng.random() < 0.5:  # "this side up" arrows
            x0, z0 = rng.uniform(0.02, max(0.03, c.width_m - 0.2)), c.height_m * 0.62
            for dx in (0.0, 0.09):
                c.rect(x0 + dx + 0.025, z0, x0 + dx + 0.04, z0 + 0.08, 0.12)
                c.rect(x0 + dx, z0 + 0.08, x0 + dx + 0.065, z0 + 0.095, 0.12)
        if rng.random() < 0.5 and c.width_m > 0.3:
            c.photo(
                rng, 0.05, 0.05, 0.05 + min(0.2, c.width_m / 3), 0.05 + min(0.15, c.height_m / 3)
            )
    return TextureLayers(albedo=to_uint8(np.asarray(img, dtype=np.float32)))

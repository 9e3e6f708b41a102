"""The indoor floor texture (kind ``indoor_floor``), with the race track taped on it.

The floor texture draws the track from its ``TrackShape`` (``params`` track), so the tape
lines lie exactly where the car drives: edge tapes at +-track_width/2 laid in strips
(slightly uneven, overlapping at joins), a dashed centre line, red-and-white kerbs on
the outside of tight corners, a chequered start line, tyre marks, and the odd sticker
and tape cross that any lab floor collects.
"""

from __future__ import annotations

import numpy as np

from monoloc.sim.indoor.canvas import Canvas, word
from monoloc.sim.indoor.track import TrackShape, centre_line, curvature_closed
from monoloc.sim.texture_tools import material, smooth_noise, to_uint8
from monoloc.sim.textures import TextureLayers, TextureSpec

FLOOR_STYLES = ("concrete", "tiles", "parquet", "carpet")


def _floor_base(rng, w, h, ppm, style, tone) -> np.ndarray:
    if style == "concrete":
        img = tone * (
            1.0
            + 0.06 * material(rng, ("gravel",), w, h, int(0.25 * ppm))
            + 0.07 * smooth_noise(rng, w, h, 0.8 * ppm)
        )
        joint = int(rng.uniform(2.5, 4.0) * ppm)
        img[::joint, :] *= 0.6
        img[:, ::joint] *= 0.6
    elif style == "tiles":
        size = int(rng.uniform(0.3, 0.6) * ppm)
        yy, xx = np.mgrid[0:h, 0:w]
        cell = (xx // size) * 7919 + (yy // size) * 104729
        tones = ((cell * 2654435761 % 1000) / 1000.0).astype(np.float32)
        img = tone * (1.0 + 0.08 * (tones - 0.5) + 0.05 * material(rng, ("gravel",), w, h, 40))
        img[(yy % size) < 2] *= 0.7
        img[(xx % size) < 2] *= 0.7
    elif style == "parquet":
        plank_w, plank_l = int(rng.uniform(0.1, 0.18) * ppm), int(rng.uniform(0.8, 1.4) * ppm)
        rows = np.arange(h) // plank_w
        shift = (rows * 7919 % 13) / 13.0 * plank_l
        xx = np.arange(w)[None, :] + shift[:, None]
        plank = (xx // plank_l).astype(np.int64) * 131 + rows[:, None]
        tones = ((plank * 2654435761 % 1000) / 1000.0).astype(np.float32)
        grain_small = rng.standard_normal((h, max(2, w // 40))).astype(np.float32)
        import cv2

        grain = cv2.resize(grain_small, (w, h), interpolation=cv2.INTER_LINEAR)
        img = tone * (1.0 + 0.25 * (tones - 0.5) + 0.05 * grain)
        img[(np.arange(h) % plank_w) < 2, :] *= 0.7
        img[(xx % plank_l) < 2] *= 0.7
    else:  # carpet tiles, pile direction alternating
        size = int(0.5 * ppm)
        pile = material(rng, ("grass", "gravel"), w, h, int(0.1 * ppm))
        yy, xx = np.mgrid[0:h, 0:w]
        flip = ((xx // size + yy // size) % 2).astype(np.float32)
        img = tone * (1.0 + 0.1 * pile + 0.06 * flip)
    # Aggregate, flecks and grit: the small blobs a floor seen from 17 cm is made of.
    spots = smooth_noise(rng, w, h, rng.uniform(1.5, 3.0))
    img = img * (1.0 - 0.18 * (spots > 1.6) + 0.14 * (spots < -1.7))
    return img.astype(np.float32)


def _to_px(xy, x_min, y_max, ppm) -> np.ndarray:
    """World (N, 2) -> cv2 drawing coordinates (pixel centres at integers), *16."""
    col = (xy[:, 0] - x_min) * ppm - 0.5
    row = (y_max - xy[:, 1]) * ppm - 0.5
    return np.round(np.stack([col, row], axis=1) * 16).astype(np.int32)


def _draw_track(img, rng, shape: TrackShape, track_w, tape_tone, x_min, y_max, ppm):
    import cv2

    xy = centre_line(shape)
    n = len(xy)
    tangent = np.roll(xy, -1, axis=0) - np.roll(xy, 1, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    left = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    kappa = curvature_closed(xy)
    step = float(np.mean(np.linalg.norm(np.diff(xy, axis=0), axis=1)))

    def line(points, tone, width_m):
        cv2.polylines(
            img,
            [_to_px(points, x_min, y_max, ppm)],
            False,
            float(tone),
            max(1, int(round(width_m * ppm))),
            cv2.LINE_AA,
            shift=4,
        )

    # Tyre marks of earlier laps along the wheel tracks.
    for side in (-0.08, 0.08):
        k = 0
        while k < n:
            length = int(rng.uniform(0.3, 2.0) / step)
            if rng.random() < 0.3:
                idx = np.arange(k, min(n, k + length))
                line(xy[idx] + left[idx] * side, float(np.mean(img)) * 0.9, 0.015)
            k += length
    tape_w = 0.04
    for side in (-1.0, 1.0):  # edge tapes, laid in strips
        k = 0
        while k < n:
            length = int(rng.uniform(0.6, 1.6) / step)
            idx = np.arange(k, min(n, k + length + 3)) % n
            jitter = rng.normal(0, 0.002)
            pts = xy[idx] + left[idx] * (side * track_w / 2 + jitter)
            line(pts, tape_tone * rng.uniform(0.93, 1.05), tape_w)
            k += length
    dash, gap = int(0.15 / step), int(0.15 / step)  # dashed centre line
    for k in range(0, n - dash, dash + gap):
        line(xy[k : k + dash], tape_tone, 0.02)
    # Kerbs outside tight corners: a band of alternating dark and light blocks.
    block = max(2, int(0.1 / step))
    for k in range(0, n - block, block):
        mean_k = float(np.mean(kappa[k : k + block]))
        if abs(mean_k) < 1.0 / 1.6:
            continue
        outside = -np.sign(mean_k)  # a left turn's outside is on the right
        inner = track_w / 2 + tape_w / 2 + 0.01
        a, b = xy[k], xy[k + block]
        la, lb = left[k] * outside, left[k + block] * outside
        corners = np.array(
            [a + la * inner, b + lb * inner, b + lb * (inner + 0.05), a + la * (inner + 0.05)]
        )
        tone = 0.9 if (k // block) % 2 else 0.25
        cv2.fillConvexPoly(
            img, _to_px(corners, x_min, y_max, ppm), float(tone), cv2.LINE_AA, shift=4
        )
    # Chequered start line across the track.
    sq = 0.04
    for i, t in enumerate(np.arange(-track_w / 2, track_w / 2, sq)):
        for j in range(2):
            p0 = xy[0] + left[0] * t + tangent[0] * sq * j
            corners = np.array(
                [p0, p0 + left[0] * sq, p0 + left[0] * sq + tangent[0] * sq, p0 + tangent[0] * sq]
            )
            tone = 0.92 if (i + j) % 2 else 0.06
            cv2.fillConvexPoly(
                img, _to_px(corners, x_min, y_max, ppm), float(tone), cv2.LINE_AA, shift=4
            )
    return xy


def floor(spec: TextureSpec, rng: np.random.Generator) -> TextureLayers:
    """Floor of a room with its track. params: ppm, style, tone (mean albedo), x_min,
    y_max (world position of the texture's top-left corner; texture x along +x, y along
    -y), track (the TrackShape as_params), track_width_m, tape_tone."""
    import cv2

    w, h = spec.width_px, spec.height_px
    ppm = float(spec.param("ppm"))
    img = _floor_base(rng, w, h, ppm, spec.param("style", "concrete"), float(spec.param("tone")))
    x_min, y_max = float(spec.param("x_min")), float(spec.param("y_max"))
    # Dust and stains.
    img *= 1.0 + 0.05 * np.clip(smooth_noise(rng, w, h, 0.3 * ppm), -2, 2)
    c = Canvas(img, ppm)  # z here is -y: used only for stickers and text
    for _ in range(int(w * h / ppm**2 * 0.6)):
        x, z = rng.uniform(0.1, c.width_m - 0.3), rng.uniform(0.1, c.height_m - 0.3)
        r = rng.random()
        if r < 0.3:  # tape cross (calibration mark)
            tone = float(rng.choice([0.9, 0.1, 0.6]))
            c.rect(x, z + 0.045, x + 0.12, z + 0.075, tone)
            c.rect(x + 0.045, z, x + 0.075, z + 0.12, tone)
        elif r < 0.55:  # label sticker
            sw, sh = rng.uniform(0.06, 0.2), rng.uniform(0.04, 0.1)
            c.rect(x, z, x + sw, z + sh, 0.92)
            c.text(rng, word(rng), x, z, x + sw, z + sh, 0.1)
        elif r < 0.75:  # stain
            cv2.circle(
                img,
                (c.col(x), c.row(z)),
                max(2, c.col(rng.uniform(0.03, 0.15))),
                float(np.mean(img) * rng.uniform(0.8, 0.95)),
                -1,
                cv2.LINE_AA,
            )
        else:  # scrap of tape
            tone = float(rng.choice([0.9, 0.15, 0.5]))
            c.rect(x, z, x + rng.uniform(0.05, 0.25), z + 0.03, tone)
    track = spec.param("track")
    if track is not None:
        shape = TrackShape.from_params(track)
        xy = _draw_track(
            img,
            rng,
            shape,
            float(spec.param("track_width_m")),
            float(spec.param("tape_tone", 0.9)),
            x_min,
            y_max,
            ppm,
        )
        # "START" written beside the start line, distance numbers every 2 m.
        left = np.array([-(xy[1] - xy[0])[1], (xy[1] - xy[0])[0]])
        left /= np.linalg.norm(left)
        p = xy[0] + left * (float(spec.param("track_width_m")) / 2 + 0.25)
        col, row = (p[0] - x_min) * ppm, (y_max - p[1]) * ppm
        c.text(
            rng,
            "START",
            (col - 0.2 * ppm) / ppm,
            c.height_m - (row + 0.06 * ppm) / ppm,
            (col + 0.2 * ppm) / ppm,
            c.height_m - (row - 0.06 * ppm) / ppm,
            0.92,
            0.15,
        )
    return TextureLayers(albedo=to_uint8(img))

"""Small image helpers for texture synthesis: the photo library and pixel utilities.

All images here are float32 in [0, 1] (gray) until a generator converts to uint8.
The photographs are scikit-image's bundled samples (no download needed).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

# Photos by what they are good for. Colour photos are turned to gray with random
# channel weights ("recolouring"), so one photo gives many different-looking crops.
MATERIAL_PHOTOS = ("brick", "gravel", "grass", "moon", "cell")
PICTURE_PHOTOS = (
    "coffee",
    "chelsea",
    "astronaut",
    "rocket",
    "camera",
    "coins",
    "clock",
    "text",
    "page",
    "immunohistochemistry",
    "hubble_deep_field",
    "stereo_motorcycle",
    "horse",
)
SHOP_WORDS = (
    "CAFE",
    "BAR",
    "PIZZA",
    "HOTEL",
    "BANK",
    "PHARMACY",
    "BAKERY",
    "BOOKS",
    "SHOES",
    "MARKT",
    "OPTIK",
    "DELI",
    "SUSHI",
    "KEBAB",
    "FLOWERS",
    "TAXI",
    "PARKING",
    "KIOSK",
    "BISTRO",
    "DENTIST",
    "LAUNDRY",
    "TOYS",
    "MUSIC",
    "FOTO",
    "GARAGE",
    "TICKETS",
    "WINE",
    "BURGER",
    "NAILS",
    "TATTOO",
    "BIKES",
    "PHONE",
    "BUTCHER",
    "TEA",
    "POST",
    "GYM",
)


@lru_cache(maxsize=1)
def photo_library() -> dict[str, np.ndarray]:
    """Name -> float32 photo in [0, 1], (H, W) gray or (H, W, 3) colour."""
    import skimage.data

    photos = {}
    for name in MATERIAL_PHOTOS + PICTURE_PHOTOS:
        image = getattr(skimage.data, name)()
        if name == "stereo_motorcycle":
            image = image[0]
        image = np.asarray(image)
        if image.dtype == bool:
            image = image.astype(np.float32) * 0.8 + 0.1
        else:
            image = image.astype(np.float32) / 255.0
        if image.ndim == 3:
            image = image[:, :, :3]
        photos[name] = image
    return photos


def photo_gray(rng: np.random.Generator, names: tuple[str, ...]) -> np.ndarray:
    """A random photo from ``names`` as (H, W) float32 gray, recoloured if colour."""
    image = photo_library()[names[int(rng.integers(len(names)))]]
    if image.ndim == 3:
        weights = rng.dirichlet([1.5, 1.5, 1.5]).astype(np.float32)
        image = image @ weights
    return image


def crop_resize(
    rng: np.random.Generator,
    image: np.ndarray,
    width: int,
    height: int,
    min_fraction: float = 0.2,
) -> np.ndarray:
    """A random crop of ``image`` (keeping the aspect ratio of the output) resized to
    (height, width), randomly mirrored."""
    import cv2

    width, height = max(1, int(width)), max(1, int(height))
    h, w = image.shape[:2]
    aspect = width / height
    frac = rng.uniform(min_fraction, 1.0)
    ch = max(2, min(h, int(frac * min(h, w / aspect))))
    cw = max(2, min(w, int(ch * aspect)))
    y = int(rng.integers(0, h - ch + 1))
    x = int(rng.integers(0, w - cw + 1))
    crop = image[y : y + ch, x : x + cw]
    interp = cv2.INTER_AREA if cw > width else cv2.INTER_LINEAR
    out = cv2.resize(crop, (width, height), interpolation=interp)
    if rng.random() < 0.5:
        out = out[:, ::-1]
    return np.ascontiguousarray(out)


def make_tileable(image: np.ndarray) -> np.ndarray:
    """Cross-fade ``image`` with a half-period shifted copy so that it tiles seamlessly."""
    h, w = image.shape[:2]
    wy = 1.0 - np.abs(np.linspace(-1.0, 1.0, h, dtype=np.float32))
    wx = 1.0 - np.abs(np.linspace(-1.0, 1.0, w, dtype=np.float32))
    weight = np.minimum(wy[:, None], wx[None, :]) * 2.0
    weight = np.clip(weight, 0.0, 1.0)
    shifted = np.roll(image, (h // 2, w // 2), axis=(0, 1))
    return weight * image + (1.0 - weight) * shifted


def material(
    rng: np.random.Generator, names: tuple[str, ...], width: int, height: int, period_px: int
) -> np.ndarray:
    """A seamless material texture of (height, width) whose pattern repeats every
    ``period_px`` pixels, normalised to zero mean and unit standard deviation."""
    import cv2

    period_px = max(8, int(period_px))
    photo = photo_gray(rng, names)
    tile = crop_resize(rng, photo, period_px, period_px, min_fraction=0.5)
    tile = make_tileable(tile)
    if rng.random() < 0.5:
        tile = tile.T.copy() if tile.shape[0] == tile.shape[1] else tile
    reps = (height // period_px + 2, width // period_px + 2)
    big = np.tile(tile, reps)
    oy, ox = int(rng.integers(period_px)), int(rng.integers(period_px))
    out = big[oy : oy + height, ox : ox + width]
    out = out - cv2.GaussianBlur(out, (0, 0), period_px / 4.0) * 0.7
    return normalise(out)


def normalise(image: np.ndarray) -> np.ndarray:
    """Zero mean, unit standard deviation (float32)."""
    image = image.astype(np.float32)
    std = float(image.std())
    return (image - float(image.mean())) / (std if std > 1e-6 else 1.0)


def smooth_noise(rng: np.random.Generator, width: int, height: int, cell_px: float) -> np.ndarray:
    """Low-frequency noise with features of about ``cell_px`` pixels, unit std, (H, W)."""
    import cv2

    gw = max(2, int(width / cell_px) + 2)
    gh = max(2, int(height / cell_px) + 2)
    grid = rng.standard_normal((gh, gw)).astype(np.float32)
    big = cv2.resize(grid, (width, height), interpolation=cv2.INTER_CUBIC)
    return normalise(big)


def to_uint8(image: np.ndarray) -> np.ndarray:
    """[0, 1] float -> uint8, clipped."""
    return np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)


def put_text_fit(
    canvas: np.ndarray,
    text: str,
    x: int,
    y: int,
    w: int,
    h: int,
    value: float,
    rng: np.random.Generator,
    thickness_frac: float = 0.12,
) -> None:
    """Draw ``text`` to fill the box (x, y, w, h) of float image ``canvas`` in place."""
    import cv2

    if w < 8 or h < 6:
        return
    fonts = (
        cv2.FONT_HERSHEY_SIMPLEX,
        cv2.FONT_HERSHEY_DUPLEX,
        cv2.FONT_HERSHEY_COMPLEX,
        cv2.FONT_HERSHEY_TRIPLEX,
        cv2.FONT_HERSHEY_PLAIN,
    )
    font = fonts[int(rng.integers(len(fonts)))]
    (tw, th), _ = cv2.getTextSize(text, font, 1.0, 1)
    scale = min(w * 0.9 / max(tw, 1), h * 0.75 / max(th, 1))
    thick = max(1, int(th * scale * thickness_frac))
    (tw, th), base = cv2.getTextSize(text, font, scale, thick)
    org = (int(x + (w - tw) / 2), int(y + (h + th) / 2))
    # putText draws on uint8 only: draw a coverage mask, then blend into the float canvas.
    mask = np.zeros(canvas.shape[:2], np.uint8)
    cv2.putText(mask, text, org, font, scale, 255, thick, cv2.LINE_AA)
    ys, xs = np.nonzero(mask)
    if len(ys):
        cover = mask[ys, xs].astype(np.float32) / 255.0
        canvas[ys, xs] = canvas[ys, xs] * (1.0 - cover) + float(value) * cover

"""Drawing in metres on an indoor texture: a wall (or furniture front) seen from the
front, x to the right from its left edge, z up from its bottom edge.

Images are float32 albedo in [0, 1] (as in ``monoloc.sim.texture_tools``); ``Canvas``
converts metres to pixels so that the painters in ``monoloc.sim.indoor.wall_textures``
read like a floor plan.
"""

from __future__ import annotations

import numpy as np

from monoloc.sim.texture_tools import PICTURE_PHOTOS, crop_resize, photo_gray, put_text_fit


class Canvas:
    """A float32 image (H, W) of ``width_m`` x ``height_m`` at ``ppm`` pixels per metre."""

    def __init__(self, image: np.ndarray, ppm: float):
        self.img = image
        self.ppm = float(ppm)
        self.h_px, self.w_px = image.shape
        self.height_m = self.h_px / self.ppm
        self.width_m = self.w_px / self.ppm

    def col(self, x_m: float) -> int:
        return int(round(x_m * self.ppm))

    def row(self, z_m: float) -> int:
        return int(round((self.height_m - z_m) * self.ppm))

    def box_px(self, x0, z0, x1, z1) -> tuple[int, int, int, int]:
        """(c0, r0, c1, r1) pixel bounds, clipped, of the box [x0, x1] x [z0, z1]."""
        c0, c1 = sorted((self.col(x0), self.col(x1)))
        r0, r1 = sorted((self.row(z1), self.row(z0)))
        return (
            max(0, c0),
            max(0, r0),
            min(self.w_px, max(c1, c0 + 1)),
            min(self.h_px, max(r1, r0 + 1)),
        )

    def rect(self, x0, z0, x1, z1, value: float) -> None:
        c0, r0, c1, r1 = self.box_px(x0, z0, x1, z1)
        if c1 > c0 and r1 > r0:
            self.img[r0:r1, c0:c1] = value

    def shade(self, x0, z0, x1, z1, factor: float) -> None:
        c0, r0, c1, r1 = self.box_px(x0, z0, x1, z1)
        self.img[r0:r1, c0:c1] *= factor

    def outline(self, x0, z0, x1, z1, value: float, width_m: float = 0.01) -> None:
        w = max(width_m, 1.0 / self.ppm)
        self.rect(x0, z0, x1, z0 + w, value)
        self.rect(x0, z1 - w, x1, z1, value)
        self.rect(x0, z0, x0 + w, z1, value)
        self.rect(x1 - w, z0, x1, z1, value)

    def paste(self, x0, z0, x1, z1, patch: np.ndarray) -> None:
        """Put ``patch`` (any size) resized into the box."""
        import cv2

        c0, r0, c1, r1 = self.box_px(x0, z0, x1, z1)
        if c1 - c0 < 2 or r1 - r0 < 2:
            return
        self.img[r0:r1, c0:c1] = cv2.resize(
            patch.astype(np.float32), (c1 - c0, r1 - r0), interpolation=cv2.INTER_AREA
        )

    def region(self, x0, z0, x1, z1) -> np.ndarray:
        """A view of the pixels of the box (writes go to the canvas)."""
        c0, r0, c1, r1 = self.box_px(x0, z0, x1, z1)
        return self.img[r0:r1, c0:c1]

    def text(self, rng, text: str, x0, z0, x1, z1, value: float, thickness: float = 0.12):
        c0, r0, c1, r1 = self.box_px(x0, z0, x1, z1)
        put_text_fit(self.img, text, c0, r0, c1 - c0, r1 - r0, value, rng, thickness)

    def photo(self, rng, x0, z0, x1, z1, low: float = 0.05, high: float = 0.95, names=None):
        """A crop of a real photograph (scikit-image samples) filling the box."""
        c0, r0, c1, r1 = self.box_px(x0, z0, x1, z1)
        if c1 - c0 < 2 or r1 - r0 < 2:
            return
        crop = crop_resize(rng, photo_gray(rng, names or PICTURE_PHOTOS), c1 - c0, r1 - r0)
        self.img[r0:r1, c0:c1] = low + (high - low) * crop


WORDS = (
    "LAB",
    "EXIT",
    "STORAGE",
    "OFFICE",
    "PRIVATE",
    "PUSH",
    "PULL",
    "FIRE DOOR",
    "KEEP CLEAR",
    "ROBOTICS",
    "BATTERIES",
    "TOOLS",
    "CABLES",
    "SPARE PARTS",
    "TIRES",
    "SENSORS",
    "LIDAR",
    "MOTORS",
    "SERVOS",
    "ESC",
    "CHARGER",
    "LIPO",
    "CAMERA",
    "MISC",
    "DO NOT TOUCH",
    "MPC LAB",
    "TEST TRACK",
    "DANGER",
    "SCREWS M3",
    "WHEELS",
)

BOARD_LINES = (
    "x += v cos(psi) dt",
    "y += v sin(psi) dt",
    "psi += gamma dt",
    "p(z|x) = sum c_i N(...)",
    "k = 10  VLAD 64x32",
    "TODO: calibrate",
    "RMSE < 0.1 m ?",
    "lap time 14.2 s",
    "deadline FRI",
    "PnP + RANSAC",
    "ORB 1000",
    "track v3",
    "meeting 2pm",
    "N = 500 particles",
    "mu1, Sigma1",
    "battery 7.4 V",
)


def word(rng: np.random.Generator, words=WORDS) -> str:
    text = words[int(rng.integers(len(words)))]
    if rng.random() < 0.35:
        text += f" {int(rng.integers(1, 40))}"
    return text

"""bench/frame_cost.py's pieces: its baseline decode (the server's previous path) gives
the product's pixels for PNG and JPEG bodies, and its summary's ratio and accuracy
figures are what the samples say."""

from __future__ import annotations

import cv2
import numpy as np

from bench.frame_cost import STAGES, bodies, decode_baseline, previous_decode, summarise
from monoloc.server.api.limits import check_image, decode_gray


def _noisy_frame(rng: np.random.Generator) -> np.ndarray:
    ramp = np.linspace(0, 200, 241)[None, :] + np.linspace(0, 40, 76)[:, None]
    return np.clip(ramp + rng.normal(0, 6, ramp.shape), 0, 255).astype(np.uint8)


def test_the_baseline_decode_gives_the_products_pixels_for_every_body():
    image = _noisy_frame(np.random.default_rng(3))
    ok, png = cv2.imencode(".png", image)
    assert ok
    made = bodies(image, png.tobytes())
    assert set(made) == {"png", "jpeg90", "jpeg75"}
    assert len(made["jpeg75"]) < len(made["jpeg90"]) < len(made["png"])
    for data in made.values():
        info = check_image(data, "image", 10**8)
        np.testing.assert_array_equal(previous_decode(data), decode_gray(data, info, "image"))
    np.testing.assert_array_equal(previous_decode(made["png"]), image)
    times = decode_baseline([(made, np.zeros(2), image)], repeats=2)
    assert all(v > 0 for row in times.values() for v in row.values())


def test_the_summary_states_the_ratio_and_the_accuracy_of_its_samples():
    samples = [
        {**dict.fromkeys(STAGES, 1.0), "features": 4.0, "total": 10.0, "wall": 12.0},
        {**dict.fromkeys(STAGES, 1.0), "features": 4.0, "total": 6.0, "wall": 8.0},
    ]
    row = summarise(samples, [0.1, float("inf")], [1024, 3072])
    assert row["total_over_features"] == 8.0 / 4.0
    assert row["share_within_0_25m"] == 0.5
    assert row["share_without_hypothesis"] == 0.5
    assert row["body_kb_mean"] == 2.0

import cv2
import numpy as np
import pytest
from skimage import data

from monoloc.core.errors import InvalidInputError
from monoloc.server.vision.binary_code import hamming_distances, vlad_binary_code
from monoloc.server.vision.features import OrbConfig, extract_features
from monoloc.server.vision.sizes import CODE_BYTES
from monoloc.server.vision.vlad import compute_vlad_batch
from monoloc.server.vision.vocabulary import load_default_vocabulary

PHOTOS = (
    "astronaut",
    "brick",
    "camera",
    "coffee",
    "chelsea",
    "rocket",
    "gravel",
    "grass",
    "coins",
    "moon",
    "clock",
    "immunohistochemistry",
    "hubble_deep_field",
    "cell",
    "cat",
)


def test_bit_order_is_numpy_big_endian_packbits():
    vlad = np.zeros(2048, dtype=np.float32)
    assert np.all(vlad_binary_code(vlad) == 0)  # zero is not positive
    vlad[0], vlad[7], vlad[8], vlad[2047], vlad[9] = 0.5, 0.1, 0.2, 0.3, -0.4
    code = vlad_binary_code(vlad)
    assert code.shape == (CODE_BYTES,) and code.dtype == np.uint8 and CODE_BYTES == 256
    assert code[0] == 0x81 and code[1] == 0x80 and code[255] == 0x01
    assert np.count_nonzero(code) == 3


def test_hamming_distance_counts_sign_disagreements():
    rng = np.random.default_rng(0)
    vlads = rng.standard_normal((20, 2048)).astype(np.float32)
    codes = vlad_binary_code(vlads)
    assert codes.shape == (20, CODE_BYTES)
    expected = np.count_nonzero((vlads > 0) != (vlads[0] > 0), axis=1)
    assert np.array_equal(hamming_distances(codes[0], codes), expected)


def test_bad_input_raises():
    for bad in (np.zeros(100), np.zeros((2, 3, 2048)), np.full(2048, np.nan), np.zeros(2048, int)):
        with pytest.raises(InvalidInputError):
            vlad_binary_code(bad)


def _window_vlads(n_windows, rng, features):
    """VLADs of random windows (30-70 % of each side) of real photos at two scales."""
    vocabulary = load_default_vocabulary()
    sets = []
    while len(sets) < n_windows:
        (h, w), feats = features[rng.integers(len(features))]
        ww, wh = int(rng.uniform(0.3, 0.7) * w), int(rng.uniform(0.3, 0.7) * h)
        x0, y0 = rng.integers(0, w - ww + 1), rng.integers(0, h - wh + 1)
        kp = feats.keypoints_px
        inside = (kp[:, 0] >= x0) & (kp[:, 0] < x0 + ww) & (kp[:, 1] >= y0) & (kp[:, 1] < y0 + wh)
        if inside.sum() >= 50:
            sets.append(feats.descriptors[inside][:1000])
    return compute_vlad_batch(sets, vocabulary)


def test_hamming_shortlist_keeps_the_exact_top10_on_real_photo_vlads():
    rng = np.random.default_rng(0)
    features = []
    for name in PHOTOS:
        image = getattr(data, name)()
        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
        for scale in (0.5, 1.0):
            scaled = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
            features.append((scaled.shape, extract_features(scaled, OrbConfig(max_features=3000))))
    database = _window_vlads(1500, rng, features)
    queries = _window_vlads(200, rng, features)

    exact = (queries**2).sum(1)[:, None] - 2 * queries @ database.T + (database**2).sum(1)[None]
    signs_db = np.unpackbits(vlad_binary_code(database), axis=1).astype(np.float32) * 2 - 1
    signs_q = np.unpackbits(vlad_binary_code(queries), axis=1).astype(np.float32) * 2 - 1
    hamming = (2048 - signs_q @ signs_db.T) / 2
    true_top10 = np.argsort(exact, axis=1, kind="stable")[:, :10]

    recalls = {}
    for shortlist_size in (10, 20, 50, 100):
        shortlist = np.argsort(hamming, axis=1, kind="stable")[:, :shortlist_size]
        reranked = np.take_along_axis(
            shortlist, np.argsort(np.take_along_axis(exact, shortlist, 1), axis=1)[:, :10], 1
        )
        recalls[shortlist_size] = np.mean(
            [len(np.intersect1d(a, b)) / 10 for a, b in zip(true_top10, reranked, strict=True)]
        )
    print(
        "recall@10 of Hamming shortlist + exact re-rank:",
        {k: round(float(v), 4) for k, v in recalls.items()},
    )
    # Measured (sign bits, default vocabulary): 10: 0.903, 20: 0.998, 50: 0.999, 100: 0.999.
    assert recalls[10] >= 0.8
    assert recalls[50] >= 0.97
    assert recalls[100] >= 0.98

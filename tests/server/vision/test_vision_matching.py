import cv2
import numpy as np
import pytest
from skimage import data

from monoloc.core.errors import InvalidInputError
from monoloc.server.vision.features import extract_features
from monoloc.server.vision.matching import (
    MatchConfig,
    match_against_references,
    match_descriptors,
    match_descriptors_bruteforce,
)


def _gray(name):
    image = getattr(data, name)()
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image


def _warped_pair(name, angle_deg, scale):
    image = _gray(name)
    h, w = image.shape
    M = cv2.getRotationMatrix2D((w / 2.0, h / 2.0), angle_deg, scale)
    return image, cv2.warpAffine(image, M, (w, h)), M


def _bits(n_set, n_bits=256):
    """A descriptor with the first n_set bits set."""
    bits = np.zeros(n_bits, dtype=np.uint8)
    bits[:n_set] = 1
    return np.packbits(bits)


@pytest.mark.parametrize("name,angle_deg,scale", [("astronaut", 20.0, 0.9), ("coffee", -35.0, 1.1)])
def test_matches_on_a_real_photo_follow_the_known_warp(name, angle_deg, scale):
    image, warped, M = _warped_pair(name, angle_deg, scale)
    a, b = extract_features(image), extract_features(warped)
    matches = match_descriptors(a.descriptors, b.descriptors)
    predicted = a.keypoints_px[matches[:, 0]] @ M[:, :2].T + M[:, 2]
    error_px = np.linalg.norm(predicted - b.keypoints_px[matches[:, 1]], axis=1)
    print(f"{name}: {len(matches)} matches, {np.mean(error_px < 3):.1%} within 3 px")
    assert len(matches) >= 100
    assert np.mean(error_px < 3.0) >= 0.8


@pytest.mark.parametrize(
    "config",
    [MatchConfig(), MatchConfig(cross_check=False), MatchConfig(ratio=0.95, max_hamming_bits=90)],
)
def test_fast_matcher_equals_opencv_bruteforce_baseline(config):
    image, warped, _ = _warped_pair("astronaut", 10.0, 1.0)
    a, b = extract_features(image), extract_features(warped)
    fast = match_descriptors(a.descriptors, b.descriptors, config)
    baseline = match_descriptors_bruteforce(a.descriptors, b.descriptors, config)
    assert fast.dtype == np.int32 and fast.shape[1] == 2 and len(fast) > 50
    assert np.array_equal(fast, baseline)


def test_batched_references_equal_one_by_one_matching():
    query = extract_features(_gray("astronaut")).descriptors
    refs = []
    for i, (angle, scale) in enumerate([(5, 1.0), (15, 0.8), (-25, 1.2), (0, 0.5)]):
        _, warped, _ = _warped_pair("astronaut", angle, scale)
        refs.append(extract_features(warped).descriptors[: 1000 - 200 * i])
    refs.append(np.zeros((0, 32), dtype=np.uint8))
    refs.append(extract_features(_gray("camera")).descriptors)
    batched = match_against_references(query, refs)
    assert len(batched) == len(refs)
    for ref, result in zip(refs, batched, strict=True):
        assert np.array_equal(result, match_descriptors(query, ref))
    assert len(batched[4]) == 0
    # An unrelated photo gives few matches compared with warped copies of the query.
    assert len(batched[5]) < 0.2 * len(batched[0])


def test_ratio_threshold_and_cross_check_rules_on_hand_made_distances():
    ref = np.stack([_bits(10), _bits(40), _bits(200)])  # distances from zeros: 10, 40, 200
    zeros = np.zeros((1, 32), dtype=np.uint8)
    # d1 = 10, d2 = 40: passes.
    assert match_descriptors(zeros, ref).tolist() == [[0, 0]]
    # Ratio test fails: d1 = 30, d2 = 35.
    ref_close = np.stack([_bits(30), _bits(35)])
    assert len(match_descriptors(zeros, ref_close)) == 0
    assert match_descriptors(zeros, ref_close, MatchConfig(ratio=0.9)).tolist() == [[0, 0]]
    # Absolute bound: d1 = 70 > 64 even though the ratio is fine.
    ref_far = np.stack([_bits(70), _bits(250)])
    assert len(match_descriptors(zeros, ref_far)) == 0
    # A single reference descriptor has no second neighbour: ratio test passes.
    assert match_descriptors(zeros, ref[:1]).tolist() == [[0, 0]]
    # Two identical queries tie for reference 0: cross check refuses both.
    two = np.zeros((2, 32), dtype=np.uint8)
    assert len(match_descriptors(two, ref)) == 0
    assert match_descriptors(two, ref, MatchConfig(cross_check=False)).tolist() == [[0, 0], [1, 0]]
    for config in (MatchConfig(), MatchConfig(cross_check=False)):
        assert np.array_equal(
            match_descriptors(two, ref, config), match_descriptors_bruteforce(two, ref, config)
        )


def test_empty_inputs_and_bad_dtypes():
    desc = extract_features(_gray("camera")).descriptors
    empty = np.zeros((0, 32), dtype=np.uint8)
    for q, r in [(empty, desc), (desc, empty), (empty, empty)]:
        for fn in (match_descriptors, match_descriptors_bruteforce):
            out = fn(q, r)
            assert out.shape == (0, 2) and out.dtype == np.int32
    assert match_against_references(empty, [desc, empty])[0].shape == (0, 2)
    assert match_against_references(desc, []) == []
    with pytest.raises(InvalidInputError):
        match_descriptors(desc.astype(np.int16), desc)
    with pytest.raises(InvalidInputError):
        match_descriptors(desc[:, :16], desc)


@pytest.mark.parametrize("seed", range(5))
def test_fast_equals_baseline_when_distances_tie_a_lot(seed):
    # Descriptors that differ from shared codes by 0-2 flipped bits: many exact ties in
    # both directions (two queries from one code tie for its reference), the case where
    # tie handling decides the result.
    rng = np.random.default_rng(seed)
    bases = rng.integers(0, 256, size=(60, 32), dtype=np.uint8)

    def draw(n):
        bits = np.unpackbits(bases[rng.integers(0, len(bases), n)], axis=1)
        for row in bits:
            row[rng.integers(0, 256, rng.integers(0, 3))] ^= 1
        return np.packbits(bits, axis=1)

    query, ref = draw(120), draw(60)
    counts = {}
    for config in (MatchConfig(), MatchConfig(ratio=1.0), MatchConfig(cross_check=False)):
        fast = match_descriptors(query, ref, config)
        assert np.array_equal(fast, match_descriptors_bruteforce(query, ref, config))
        counts[config.cross_check] = len(fast)
    # The cross check has real work to do here: it removes most tied pairs.
    assert 5 <= counts[True] < counts[False] / 2

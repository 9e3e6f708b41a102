import cv2
import numpy as np
import pytest
from skimage import data

from monoloc.core.errors import InvalidInputError
from monoloc.server.vision.features import extract_features
from monoloc.server.vision.sizes import VLAD_DIM
from monoloc.server.vision.vlad import (
    assign_words,
    compute_vlad,
    compute_vlad_batch,
    vlad_distance,
)
from monoloc.server.vision.vocabulary import Vocabulary, load_default_vocabulary


def _descriptors(name):
    image = getattr(data, name)()
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    return extract_features(image).descriptors


def _naive_vlad(descriptors, centres):
    """docs/method.md section 4 written as plainly as possible (loops, float64)."""
    x = descriptors.astype(np.float64)
    c = centres.astype(np.float64)
    sums = np.zeros_like(c)
    for row in x:
        k = int(np.argmin([np.sum((row - ck) ** 2) for ck in c]))
        sums[k] += row - c[k]
    for k in range(len(c)):
        norm = np.linalg.norm(sums[k])
        if norm > 0:
            sums[k] /= norm
    total = np.linalg.norm(sums)
    return (sums / total if total > 0 else sums).ravel()


def test_matches_a_plain_loop_implementation_on_a_real_photo():
    vocabulary = load_default_vocabulary()
    descriptors = _descriptors("coffee")
    vlad = compute_vlad(descriptors, vocabulary)
    assert vlad.shape == (VLAD_DIM,) and vlad.dtype == np.float32
    assert np.allclose(vlad, _naive_vlad(descriptors, vocabulary.centres), atol=1e-6)


def test_unit_norm_and_each_used_word_row_has_norm_one_over_sqrt_of_rows():
    vocabulary = load_default_vocabulary()
    # A subset of descriptors so that some words stay empty.
    descriptors = _descriptors("astronaut")[:40]
    vlad = compute_vlad(descriptors, vocabulary)
    rows = vlad.reshape(64, 32)
    used = np.zeros(64, dtype=bool)
    used[assign_words(descriptors, vocabulary)] = True
    row_norms = np.linalg.norm(rows, axis=1)
    assert 0 < used.sum() < 64
    assert np.linalg.norm(vlad) == pytest.approx(1.0, abs=1e-6)
    # Intra-normalisation makes each non-empty row unit length; the global norm is then
    # sqrt(R) for R non-empty rows, so each ends at 1/sqrt(R). Empty words stay zero.
    assert np.allclose(row_norms[used], 1.0 / np.sqrt(used.sum()), atol=1e-6)
    assert np.all(rows[~used] == 0.0)


def test_invariant_to_descriptor_order():
    vocabulary = load_default_vocabulary()
    descriptors = _descriptors("chelsea")
    shuffled = descriptors[np.random.default_rng(0).permutation(len(descriptors))]
    assert np.allclose(
        compute_vlad(descriptors, vocabulary), compute_vlad(shuffled, vocabulary), atol=1e-7
    )


def test_hand_computed_two_word_case():
    centres = np.stack([np.zeros(32), np.full(32, 200.0)])
    vocabulary = Vocabulary.from_centres(centres)
    descriptors = np.stack([np.full(32, 10), np.full(32, 30), np.full(32, 190)]).astype(np.uint8)
    # Word 0 collects 10 + 30 = +40 per entry, word 1 collects 190 - 200 = -10 per entry.
    # Each row normalises to +-1/sqrt(32); the two unit rows then share 1/sqrt(2).
    expected = np.concatenate([np.full(32, 1 / 8.0), np.full(32, -1 / 8.0)])
    vlad = compute_vlad(descriptors, vocabulary)
    assert vlad.shape == (64,)
    assert np.allclose(vlad, expected, atol=1e-7)
    # Plain centres are accepted too, with the same result.
    assert np.allclose(compute_vlad(descriptors, centres), expected, atol=1e-7)


def test_near_ties_are_decided_in_float64_and_exact_ties_go_to_the_lowest_word():
    # Scores of these centres are ~1.3e6 in float32 (ulp 0.125): the 0.002 by which word 2
    # is nearer than word 1 is below float32's resolution, so only the exact re-decision
    # can find it.
    base = np.full(32, 200.0)
    centres = np.stack([np.zeros(32), base, base, np.full(32, 100.0)]).astype(np.float32)
    centres[1, 0], centres[2, 0] = 199.0, 200.999
    descriptors = np.full((3, 32), 200, dtype=np.uint8)
    distances = ((descriptors[:1] - centres.astype(np.float64)) ** 2).sum(axis=1)
    assert distances[2] < distances[1] < distances[2] + 0.01
    assert assign_words(descriptors, centres).tolist() == [2, 2, 2]
    assert np.allclose(compute_vlad(descriptors, centres), _naive_vlad(descriptors, centres))
    # Words 1 and 2 exactly as far (1.0) from the descriptor: the lower index wins.
    centres[2, 0] = 201.0
    assert assign_words(descriptors, centres).tolist() == [1, 1, 1]


def test_zero_residuals_and_no_descriptors_give_the_zero_vector():
    centres = np.stack([np.zeros(32), np.full(32, 100.0)])
    on_centre = np.full((3, 32), 100, dtype=np.uint8)
    assert np.all(compute_vlad(on_centre, centres) == 0.0)
    empty = compute_vlad(np.zeros((0, 32), dtype=np.uint8), load_default_vocabulary())
    assert empty.shape == (VLAD_DIM,) and np.all(empty == 0.0)


def test_batch_equals_single_images():
    vocabulary = load_default_vocabulary()
    sets = [_descriptors("camera"), np.zeros((0, 32), np.uint8), _descriptors("coins")[:7]]
    batch = compute_vlad_batch(sets, vocabulary)
    assert batch.shape == (3, VLAD_DIM)
    for row, descriptors in zip(batch, sets, strict=True):
        assert np.array_equal(row, compute_vlad(descriptors, vocabulary))
    assert compute_vlad_batch([], vocabulary).shape == (0, VLAD_DIM)


def test_distance_ranks_a_warped_copy_before_an_unrelated_photo():
    vocabulary = load_default_vocabulary()
    image = cv2.cvtColor(data.astronaut(), cv2.COLOR_RGB2GRAY)
    M = cv2.getRotationMatrix2D((256, 256), 15, 0.9)
    warped = cv2.warpAffine(image, M, (512, 512))
    v_image = compute_vlad(extract_features(image).descriptors, vocabulary)
    v_warped = compute_vlad(extract_features(warped).descriptors, vocabulary)
    v_other = compute_vlad(_descriptors("brick"), vocabulary)
    assert vlad_distance(v_image, v_image) == 0.0
    assert vlad_distance(v_image, v_warped) == pytest.approx(vlad_distance(v_warped, v_image))
    assert vlad_distance(v_image, v_warped) < vlad_distance(v_image, v_other)
    assert vlad_distance(v_image, v_other) == pytest.approx(
        float(np.linalg.norm(v_image.astype(np.float64) - v_other)), rel=1e-12
    )


def test_bad_inputs_raise():
    vocabulary = load_default_vocabulary()
    with pytest.raises(InvalidInputError):
        compute_vlad(np.zeros((5, 32), dtype=np.float32), vocabulary)
    with pytest.raises(InvalidInputError):
        compute_vlad(np.zeros((5, 31), dtype=np.uint8), vocabulary)
    with pytest.raises(InvalidInputError):
        compute_vlad(np.zeros((5, 32), dtype=np.uint8), np.zeros((4, 16)))
    with pytest.raises(InvalidInputError):
        vlad_distance(np.zeros(4), np.zeros(5))

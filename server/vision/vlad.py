"""VLAD image descriptors (docs/method.md section 4): a float32 GEMM, then compiled passes.

For an image with ORB descriptors x_n (bytes as a 32-d vector) and centres c_k:
1. a_n = argmin_k ||x_n - c_k||_2            (nearest centre, L2 in byte space)
2. V_k = sum_{n: a_n = k} (x_n - c_k)        (K x 32 residual sums)
3. V_k <- V_k / ||V_k||  when ||V_k|| > 0     (intra-normalisation; zero rows stay zero)
4. v = vec(V) / ||vec(V)||                   (global L2; all-zero stays all-zero)

Consequence used by the tests: after step 3 every non-zero row has norm 1, so with R
non-zero rows step 4 divides by sqrt(R) and each non-zero row ends with norm 1/sqrt(R).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.server.vision.sizes import DESCRIPTOR_BYTES
from monoloc.server.vision.vocabulary import Vocabulary


def _centres(vocabulary: Vocabulary | np.ndarray) -> np.ndarray:
    if isinstance(vocabulary, Vocabulary):
        return vocabulary.centres
    centres = np.ascontiguousarray(vocabulary, dtype=np.float32)
    if centres.ndim != 2 or centres.shape[1] != DESCRIPTOR_BYTES or len(centres) == 0:
        raise InvalidInputError(f"vocabulary centres must be (K, 32), got {centres.shape}")
    return centres


def _check_descriptors(descriptors: np.ndarray, what: str = "descriptors") -> np.ndarray:
    descriptors = np.asarray(descriptors)
    if descriptors.dtype != np.uint8 or descriptors.ndim != 2 or descriptors.shape[1] != 32:
        raise InvalidInputError(
            f"{what} must be (N, 32) uint8, got {descriptors.shape} {descriptors.dtype}"
        )
    return descriptors


# Bound on the float32 error of a squared-distance score ||c||^2 - 2 x.c for byte-valued
# x (|x.c| <= 32 * 255 * 255 ~ 2.1e6, float32 ulp there 0.25; a float32 dot product of 32
# terms stays below ~10, whatever its summation order). Rows whose best two scores are
# closer than this are re-decided in float64, so the float32 fast path never changes an
# assignment.
_TIE_MARGIN = 16.0

_CHUNK_ROWS = 1024

# Why cv2.gemm rather than ``@``: these products are tiny (1000 x 32 x 64) and numpy's
# OpenBLAS splits them over its thread pool; on a loaded 2-core machine the hand-off costs
# many times the product itself, with a long tail. OpenCV's gemm runs in the calling
# thread and stays flat under load (bench/vision.py). Everything around it is compiled
# (``_vlad_kernel``): in numpy its small operations cost several times the product.


def _assign(descriptors: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Words (N,) int64 of C-contiguous (N, 32) uint8 descriptors; centres (K, 32) float32."""
    import cv2

    from monoloc.server.vision._vlad_kernel import nearest_words

    words = np.empty(len(descriptors), dtype=np.int64)
    for lo in range(0, len(descriptors), _CHUNK_ROWS):  # chunks keep the scores in cache
        chunk = descriptors[lo : lo + _CHUNK_ROWS]
        # -2 x.c: scaling by -2 is exact, so this is the score's product term as is
        products = cv2.gemm(chunk.astype(np.float32), centres, -2.0, None, 0.0, flags=cv2.GEMM_2_T)
        nearest_words(chunk, products, centres, _TIE_MARGIN, words[lo : lo + len(chunk)])
    return words


def assign_words(descriptors: np.ndarray, vocabulary: Vocabulary | np.ndarray) -> np.ndarray:
    """Nearest centre (L2 in byte space) of each (N, 32) uint8 descriptor -> (N,) int64.

    Scores are computed in float32; any row whose two best scores lie within the float32
    error bound is recomputed exactly in float64. Exact ties go to the lowest word index.
    """
    centres = _centres(vocabulary)
    return _assign(np.ascontiguousarray(_check_descriptors(descriptors)), centres)


def compute_vlad_batch(
    descriptor_sets: Sequence[np.ndarray], vocabulary: Vocabulary | np.ndarray
) -> np.ndarray:
    """VLADs of several images at once: B arrays (N_b, 32) uint8 -> (B, K*32) float32.

    Row b equals ``compute_vlad(descriptor_sets[b], vocabulary)``; one word assignment
    serves the whole batch.
    """
    centres = _centres(vocabulary)
    sets = [_check_descriptors(d, f"descriptor set {i}") for i, d in enumerate(descriptor_sets)]
    if not sets:
        return np.zeros((0, len(centres) * DESCRIPTOR_BYTES), dtype=np.float32)
    from monoloc.server.vision._vlad_kernel import vlads_from_words

    all_descriptors = np.ascontiguousarray(np.concatenate(sets) if len(sets) > 1 else sets[0])
    words = _assign(all_descriptors, centres)
    bounds = np.cumsum([0] + [len(d) for d in sets], dtype=np.int64)
    vlads = np.empty((len(sets), len(centres) * DESCRIPTOR_BYTES), dtype=np.float32)
    vlads_from_words(all_descriptors, words, bounds, centres, vlads)
    return vlads


def compute_vlad(descriptors: np.ndarray, vocabulary: Vocabulary | np.ndarray) -> np.ndarray:
    """VLAD of one image: (N, 32) uint8 ORB descriptors -> (K*32,) float32, unit norm.

    K = 64 for docs/method.md's vocabulary (2048 values); N = 0 gives the all-zero vector.
    Row-major: entries [32k, 32k+32) belong to word k.
    """
    return compute_vlad_batch([descriptors], vocabulary)[0]


def vlad_distance(vlad_a: np.ndarray, vlad_b: np.ndarray) -> float:
    """L2 (Frobenius) distance of two VLADs: docs/method.md's e_vlad."""
    a = np.asarray(vlad_a, dtype=np.float64)
    b = np.asarray(vlad_b, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 1:
        raise InvalidInputError(f"VLADs must be equal-length vectors, got {a.shape}, {b.shape}")
    return float(np.linalg.norm(a - b))

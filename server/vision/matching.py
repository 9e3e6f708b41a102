"""Hamming matching of ORB descriptors between a query and reference images (docs/method.md 6.3).

The match rule (both implementations below apply exactly this rule, so their outputs are
identical, not just similar):

query descriptor i and reference descriptor j are matched iff
1. j is i's nearest reference descriptor, at d1 = d(i, j) <= ``max_hamming_bits``;
2. Lowe's ratio test: d1 < ``ratio`` * d2, d2 the distance to i's second-nearest reference
   descriptor (infinite when the reference has one descriptor). With ratio < 1 this also
   makes j i's *unique* nearest neighbour;
3. with ``cross_check``: i is j's unique nearest query descriptor (no other query
   descriptor at distance <= d1 from j).

The rule never depends on how an implementation breaks ties, which is why (3) asks for
uniqueness rather than "the argmin". Output rows are sorted by query index.

Speed: OpenCV's ``BFMatcher.knnMatch`` plus its cross check is the slowest way; FAISS's
``hammings`` fills the whole distance matrix with a scalar popcount and the rule is then
applied to it with numpy. The fast path (``monoloc.server.vision._hamming_kernel``, numba)
computes the distances with a vectorised popcount and applies the rule in the same pass
without storing the matrix. ``match_descriptors_bruteforce`` keeps the OpenCV baseline and
:func:`hamming_matrix` (FAISS) the exhaustive distance floor; bench/vision.py prints all
three.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from monoloc.core.errors import InvalidInputError

_NO_MATCHES = np.zeros((0, 2), dtype=np.int32)


@dataclass(frozen=True)
class MatchConfig:
    """Hamming matching rule: ratio test, absolute bound and mutual check (see module doc)."""

    ratio: float = 0.8
    max_hamming_bits: int = 64
    cross_check: bool = True

    def __post_init__(self) -> None:
        if not 0.0 < self.ratio <= 1.0:
            raise InvalidInputError(f"MatchConfig.ratio must be in (0, 1], got {self.ratio}")
        if not 0 <= self.max_hamming_bits <= 256:
            raise InvalidInputError(
                f"MatchConfig.max_hamming_bits must be in [0, 256], got {self.max_hamming_bits}"
            )


def _check(descriptors: np.ndarray, what: str) -> np.ndarray:
    descriptors = np.asarray(descriptors)
    if descriptors.dtype != np.uint8 or descriptors.ndim != 2 or descriptors.shape[1] != 32:
        raise InvalidInputError(
            f"{what} descriptors must be (N, 32) uint8, got {descriptors.shape} {descriptors.dtype}"
        )
    return np.ascontiguousarray(descriptors)


def hamming_matrix(
    query_desc: np.ndarray, ref_desc: np.ndarray, out: np.ndarray | None = None
) -> np.ndarray:
    """All pairwise Hamming distances: (N, 32) and (M, 32) uint8 -> (N, M) int32.

    ``out`` (a C-contiguous int32 buffer of at least N * M elements) avoids allocating.
    """
    import faiss

    n, m = len(query_desc), len(ref_desc)
    if out is None:
        out = np.empty(n * m, dtype=np.int32)
    distances = out.reshape(-1)[: n * m].reshape(n, m)
    if n and m:
        faiss.hammings(
            faiss.swig_ptr(query_desc),
            faiss.swig_ptr(ref_desc),
            n,
            m,
            32,
            faiss.swig_ptr(distances),
        )
    return distances


class _Scratch:
    """Buffers the kernel writes into, sized for N query and M reference descriptors."""

    def __init__(self, n: int, m: int) -> None:
        self.ref_words_t = np.empty((4, m), dtype=np.uint64)
        self.row = np.empty(m, dtype=np.int32)
        self.col_min1 = np.empty(m, dtype=np.int32)
        self.col_min2 = np.empty(m, dtype=np.int32)
        self.pairs = np.empty((n, 2), dtype=np.int32)
        self.out_d = np.empty(n, dtype=np.int32)


def _match_words(
    match_rows, query_words: np.ndarray, ref_desc: np.ndarray, config: MatchConfig, scratch
) -> np.ndarray:
    """(K, 2) int32 matches of (N, 4) uint64 query words against (M, 32) uint8 reference
    descriptors, by the compiled kernel ``match_rows`` (imported once by the caller)."""
    if len(query_words) == 0 or len(ref_desc) == 0:
        return _NO_MATCHES.copy()
    k = match_rows(
        query_words,
        ref_desc.view(np.uint64),
        int(config.max_hamming_bits),
        float(config.ratio),
        bool(config.cross_check),
        scratch.ref_words_t,
        scratch.row,
        scratch.col_min1,
        scratch.col_min2,
        scratch.pairs,
        scratch.out_d,
    )
    return scratch.pairs[:k].copy()


def match_descriptors(
    query_desc: np.ndarray, ref_desc: np.ndarray, config: MatchConfig = MatchConfig()
) -> np.ndarray:
    """Match (N, 32) query to (M, 32) reference uint8 ORB descriptors.

    Returns (K, 2) int32 rows [query_idx, ref_idx], sorted by query index. Memory: O(N + M)
    (the distance matrix is never stored).
    """
    from monoloc.server.vision._hamming_kernel import match_rows

    query_desc, ref_desc = _check(query_desc, "query"), _check(ref_desc, "reference")
    scratch = _Scratch(len(query_desc), len(ref_desc))
    return _match_words(match_rows, query_desc.view(np.uint64), ref_desc, config, scratch)


def match_against_references(
    query_desc: np.ndarray, refs: Sequence[np.ndarray], config: MatchConfig = MatchConfig()
) -> list[np.ndarray]:
    """Match one query against several references: list of (K_r, 2) int32, one per ref.

    The ratio test and the cross check are per reference (a search over the concatenated
    references would compare the second-nearest across images, which is wrong), so each
    reference gets its own pass; the scratch buffers are shared by all of them.
    """
    from monoloc.server.vision._hamming_kernel import match_rows

    query_desc = _check(query_desc, "query")
    ref_arrays = [_check(r, f"reference {i}") for i, r in enumerate(refs)]
    largest = max((len(r) for r in ref_arrays), default=0)
    scratch = _Scratch(len(query_desc), largest)
    query_words = query_desc.view(np.uint64)
    return [
        _match_words(match_rows, query_words, ref_desc, config, scratch) for ref_desc in ref_arrays
    ]


def match_against_references_bruteforce(
    query_desc: np.ndarray, refs: Sequence[np.ndarray], config: MatchConfig = MatchConfig()
) -> list[np.ndarray]:
    """Baseline of :func:`match_against_references`: one OpenCV brute-force matcher per
    reference (:func:`match_descriptors_bruteforce`), same output."""
    return [match_descriptors_bruteforce(query_desc, ref_desc, config) for ref_desc in refs]


def match_descriptors_bruteforce(
    query_desc: np.ndarray, ref_desc: np.ndarray, config: MatchConfig = MatchConfig()
) -> np.ndarray:
    """Baseline: the same rule with OpenCV's ``BFMatcher(NORM_HAMMING).knnMatch`` (k = 2,
    and k = 2 from the reference side for the cross check). Same output as
    :func:`match_descriptors`."""
    import cv2

    query_desc, ref_desc = _check(query_desc, "query"), _check(ref_desc, "reference")
    if len(query_desc) == 0 or len(ref_desc) == 0:
        return _NO_MATCHES.copy()
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=False)
    forward = matcher.knnMatch(query_desc, ref_desc, k=2)
    candidates = {}
    for pair in forward:
        if not pair:
            continue
        best = pair[0]
        d2 = pair[1].distance if len(pair) > 1 else np.inf
        if best.distance <= config.max_hamming_bits and best.distance < config.ratio * d2:
            candidates[best.queryIdx] = (best.trainIdx, best.distance)
    if config.cross_check and candidates:
        backward = matcher.knnMatch(ref_desc, query_desc, k=2)
        accepted = {}
        for query_idx, (ref_idx, d1) in candidates.items():
            pair = backward[ref_idx]
            second = pair[1].distance if len(pair) > 1 else np.inf
            if pair[0].distance == d1 and second > d1:
                accepted[query_idx] = (ref_idx, d1)
        candidates = accepted
    if not candidates:
        return _NO_MATCHES.copy()
    return np.array([[q, candidates[q][0]] for q in sorted(candidates)], dtype=np.int32).reshape(
        -1, 2
    )

"""Compiled VLAD word decisions and residual sums (numba). Imported lazily by
monoloc.server.vision.vlad.

The products x.c come from a float32 GEMM (``vlad.assign_words``); these loops do the
rest in one pass each, where numpy needed an argmin, a gather, a tie test over the whole
score matrix, two bincounts and their temporaries, several times the arithmetic on a
query's ~1000 x 64 scores.

Exactness is ``vlad.assign_words``'s contract: a descriptor whose two best float32
scores ||c||^2 - 2 x.c lie within ``tie_margin`` (the float32 error bound) is re-decided
on float64 squared distances, ties to the lowest word index. The sums of bytes are
integers, exact in float64 in any order; the centre term is subtracted as
``count * centre``, one product and one difference, as numpy's expression does.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, boundscheck=False)
def nearest_words(descriptors, minus_two_products, centre_sq, centres64, tie_margin, words):
    """Fill words (N,) int64 with the nearest centre of each (N, D) uint8 descriptor, given
    minus_two_products (N, K) float32 = -2 x.c, centre_sq (K,) float32 = ||c||^2 and
    centres64 (K, D) float64 (for the re-decided rows)."""
    n_words, dim = centres64.shape
    scores = np.empty(n_words, dtype=np.float32)
    for n in range(descriptors.shape[0]):
        # Branch-free passes (they vectorise): the scores and their minimum, then how many
        # lie within the margin of it; only then the minimum's first index.
        best_score = np.float32(np.inf)
        for k in range(n_words):
            score = minus_two_products[n, k] + centre_sq[k]
            scores[k] = score
            best_score = min(best_score, score)
        limit = best_score + np.float32(tie_margin)
        close = 0
        for k in range(n_words):
            close += scores[k] <= limit
        best = 0
        while best < n_words - 1 and scores[best] > best_score:
            best += 1
        unsure = close > 1
        if unsure:
            best_dist = np.inf
            for k in range(n_words):
                dist = 0.0
                for d in range(dim):
                    diff = np.float64(descriptors[n, d]) - centres64[k, d]
                    dist += diff * diff
                if dist < best_dist:
                    best, best_dist = k, dist
        words[n] = best


@njit(cache=True, nogil=True, boundscheck=False)
def residual_sums(descriptors, words, bounds, centres64, sums):
    """Fill sums (B, K, D) float64 with sum_{n in set b, a_n = k} (x_n - c_k), the sets
    being the rows [bounds[b], bounds[b + 1]) of the (N, D) uint8 descriptors."""
    n_words, dim = centres64.shape
    counts = np.empty(n_words)
    for b in range(len(bounds) - 1):
        counts[:] = 0.0
        sums[b] = 0.0
        for n in range(bounds[b], bounds[b + 1]):
            k = words[n]
            counts[k] += 1.0
            for d in range(dim):
                sums[b, k, d] += np.float64(descriptors[n, d])
        for k in range(n_words):
            for d in range(dim):
                sums[b, k, d] = sums[b, k, d] - counts[k] * centres64[k, d]

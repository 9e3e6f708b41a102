"""Compiled VLAD word decisions, residual sums and normalisation (numba). Imported lazily
by monoloc.server.vision.vlad.

The products -2 x.c come from a float32 GEMM (``vlad._assign``); these loops do the
rest, where numpy needed per call a dozen small operations (centre terms, argmin, gather,
tie test over the score matrix, two bincounts, two einsum norms, divisions) and their
temporaries: a query's arithmetic (~1000 x 64 scores, 64 x 32 sums) is far smaller than
their overhead, above all when they run right after ORB with cold caches.

Exactness is ``vlad.assign_words``'s contract: a descriptor whose two best float32
scores ||c||^2 - 2 x.c lie within ``tie_margin`` (the float32 error bound) is re-decided
on float64 squared distances, ties to the lowest word index. The sums of bytes are
integers, exact in float64 in any order.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, boundscheck=False)
def nearest_words(descriptors, minus_two_products, centres, tie_margin, words):
    """Fill words (N,) int64 with the nearest centre of each (N, D) uint8 descriptor, given
    minus_two_products (N, K) float32 = -2 x.c and the centres (K, D) float32."""
    n_words, dim = centres.shape
    centres64 = np.empty((n_words, dim))
    centre_sq = np.empty(n_words, dtype=np.float32)
    for k in range(n_words):
        acc = 0.0
        for d in range(dim):
            c = np.float64(centres[k, d])
            centres64[k, d] = c
            acc += c * c
        centre_sq[k] = np.float32(acc)
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
        if close > 1:
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
def vlads_from_words(descriptors, words, bounds, centres, vlads):
    """Fill vlads (B, K * D) float32 with the VLADs of the sets of rows [bounds[b],
    bounds[b + 1]) of the (N, D) uint8 descriptors with words (N,): residual sums
    sum_{a_n = k} (x_n - c_k) in float64 (bytes summed, minus count * centre), each
    non-zero row scaled to unit norm, then the whole to unit norm (zeros stay zeros)."""
    n_words, dim = centres.shape
    sums = np.empty((n_words, dim))
    counts = np.empty(n_words)
    for b in range(len(bounds) - 1):
        sums[:, :] = 0.0
        counts[:] = 0.0
        for n in range(bounds[b], bounds[b + 1]):
            k = words[n]
            counts[k] += 1.0
            for d in range(dim):
                sums[k, d] += np.float64(descriptors[n, d])
        total = 0.0
        for k in range(n_words):
            row = 0.0
            for d in range(dim):
                value = sums[k, d] - counts[k] * np.float64(centres[k, d])
                sums[k, d] = value
                row += value * value
            norm = np.sqrt(row)
            if norm > 0.0:
                for d in range(dim):
                    sums[k, d] /= norm
                    total += sums[k, d] * sums[k, d]
        norm = np.sqrt(total)
        if not norm > 0.0:
            norm = 1.0
        for k in range(n_words):
            for d in range(dim):
                vlads[b, k * dim + d] = np.float32(sums[k, d] / norm)

"""Compiled exhaustive Hamming scan with top-n selection (numba). Imported lazily.

Codes are 256 bits, stored transposed as (4, capacity) uint64 words, so that the scan's
inner loop runs over entries with one vector lane per entry (AVX2 nibble-table popcount
on the dev box, as in server.vision._hamming_kernel). Selection avoids sorting a million
distances: the scan also keeps each block's minimum; a histogram of the block minima
gives a threshold T under which at least n entries lie (each block whose minimum is <= T
holds one); only those blocks are revisited (their distances recomputed) to collect
their entries <= T, and a counting sort over the few candidates returns the n nearest in
distance order.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from server.vision._bits import popcount64 as _popcount64

BLOCK = 64


@njit(inline="always")
def _distance(q0, q1, q2, q3, codes_t, j):
    return np.int32(
        _popcount64(q0 ^ codes_t[0, j])
        + _popcount64(q1 ^ codes_t[1, j])
        + _popcount64(q2 ^ codes_t[2, j])
        + _popcount64(q3 ^ codes_t[3, j])
    )


@njit(cache=True, nogil=True, boundscheck=False)
def scan(query_words, codes_t, lo, hi, block_min):
    """Minimum Hamming distance of query_words (4,) uint64 to each block of BLOCK codes in
    codes_t[:, lo:hi] into block_min[lo // BLOCK ...] (int32). The distances themselves
    are not stored: :func:`select_nearest` recomputes them for the few blocks it keeps.
    ``lo`` must be a multiple of BLOCK; disjoint ranges may run in parallel."""
    q0, q1, q2, q3 = query_words[0], query_words[1], query_words[2], query_words[3]
    for b in range(lo // BLOCK, (hi + BLOCK - 1) // BLOCK):
        low = np.int32(1 << 20)
        for j in range(b * BLOCK, min(b * BLOCK + BLOCK, hi)):
            low = min(low, _distance(q0, q1, q2, q3, codes_t, j))
        block_min[b] = low


@njit(cache=True, nogil=True, boundscheck=False)
def select_nearest(query_words, codes_t, block_min, n_codes, n_wanted, out_rows):
    """The ``n_wanted`` rows of codes_t[:, :n_codes] nearest to query_words, given the
    block minima written by :func:`scan`, into out_rows (int64), nearest first (ties in
    row order). Returns how many were written (min(n_wanted, n_codes))."""
    q0, q1, q2, q3 = query_words[0], query_words[1], query_words[2], query_words[3]
    n_blocks = (n_codes + BLOCK - 1) // BLOCK
    n_wanted = min(n_wanted, n_codes)
    if n_wanted <= 0:
        return 0
    histogram = np.zeros(258, dtype=np.int64)
    for b in range(n_blocks):
        histogram[block_min[b]] += 1
    # Smallest threshold with n_wanted blocks at or under it (each holds an entry <= it);
    # with fewer blocks than n_wanted, every block (threshold 256: every entry).
    threshold, covered = 0, histogram[0]
    while covered < n_wanted and threshold < 256:
        threshold += 1
        covered += histogram[threshold]
    # Gather the entries <= threshold of the blocks that can hold them, then a stable
    # counting sort by distance.
    kept = np.empty(min(covered * BLOCK, n_codes), dtype=np.int64)
    kept_d = np.empty(len(kept), dtype=np.int32)
    n_kept = 0
    counts = np.zeros(258, dtype=np.int64)
    block = np.empty(BLOCK, dtype=np.int32)
    for b in range(n_blocks):
        if block_min[b] <= threshold:
            start = b * BLOCK
            stop = min(start + BLOCK, n_codes)
            for j in range(start, stop):  # vectorised, then filtered one by one
                block[j - start] = _distance(q0, q1, q2, q3, codes_t, j)
            for j in range(start, stop):
                d = block[j - start]
                if d <= threshold:
                    kept[n_kept] = j
                    kept_d[n_kept] = d
                    n_kept += 1
                    counts[d + 1] += 1
    for d in range(1, 258):
        counts[d] += counts[d - 1]  # counts[d] = first output slot of distance d
    written = 0
    for t in range(n_kept):
        d = kept_d[t]
        slot = counts[d]
        counts[d] += 1
        if slot < n_wanted:
            out_rows[slot] = kept[t]
            written += 1
    return written


@njit(cache=True, nogil=True, boundscheck=False)
def hamming_rows(query_words, codes_words, rows, out):
    """Hamming distances of query_words (W,) uint64 to codes_words[rows] ((N, W) uint64
    codes gathered by row) into out (len(rows),) int32."""
    n_words = query_words.shape[0]
    for k in range(rows.shape[0]):
        row = rows[k]
        d = np.uint64(0)
        for w in range(n_words):
            d += _popcount64(query_words[w] ^ codes_words[row, w])
        out[k] = np.int32(d)

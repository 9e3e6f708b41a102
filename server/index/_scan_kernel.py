"""Compiled exhaustive Hamming scan with top-n selection (numba). Imported lazily.

Codes are 256 bits, stored transposed as (4, capacity) uint64 words, so that the scan's
inner loop runs over entries with one vector lane per entry (AVX2 nibble-table popcount
on the dev box, as in server.vision._hamming_kernel). Selection avoids sorting a million
distances: the scan also keeps each block's minimum; a histogram of the block minima
gives a threshold T under which at least n entries lie (each block whose minimum is <= T
holds one); only those blocks are revisited to collect their entries <= T, and a
counting sort over the few candidates returns the n nearest in distance order.
"""

from __future__ import annotations

import numpy as np
from numba import njit

BLOCK = 32
_M1 = np.uint64(0x5555555555555555)
_M2 = np.uint64(0x3333333333333333)
_M4 = np.uint64(0x0F0F0F0F0F0F0F0F)
_H01 = np.uint64(0x0101010101010101)


@njit(inline="always")
def _popcount64(x):
    x = x - ((x >> np.uint64(1)) & _M1)
    x = (x & _M2) + ((x >> np.uint64(2)) & _M2)
    x = (x + (x >> np.uint64(4))) & _M4
    return (x * _H01) >> np.uint64(56)


@njit(cache=True, nogil=True, boundscheck=False)
def scan(query_words, codes_t, lo, hi, distances, block_min):
    """Hamming distances of query_words (4,) uint64 to the codes codes_t[:, lo:hi] into
    distances[lo:hi] (int32), and each block's minimum into block_min[lo // BLOCK ...]
    (int32). ``lo`` must be a multiple of BLOCK; disjoint ranges may run in parallel."""
    q0, q1, q2, q3 = query_words[0], query_words[1], query_words[2], query_words[3]
    for b in range(lo // BLOCK, (hi + BLOCK - 1) // BLOCK):
        start = b * BLOCK
        stop = min(start + BLOCK, hi)
        low = np.int32(1 << 20)
        for j in range(start, stop):
            d = np.int32(
                _popcount64(q0 ^ codes_t[0, j])
                + _popcount64(q1 ^ codes_t[1, j])
                + _popcount64(q2 ^ codes_t[2, j])
                + _popcount64(q3 ^ codes_t[3, j])
            )
            distances[j] = d
            low = min(low, d)
        block_min[b] = low


@njit(cache=True, nogil=True, boundscheck=False)
def select_nearest(distances, block_min, n_codes, n_wanted, out_rows):
    """The ``n_wanted`` rows of the smallest distances[:n_codes] (block minima as written
    by :func:`scan`) into out_rows (int64), nearest first (ties in row order). Returns
    how many were written (min(n_wanted, n_codes))."""
    n_blocks = (n_codes + BLOCK - 1) // BLOCK
    n_wanted = min(n_wanted, n_codes)
    if n_wanted <= 0:
        return 0
    histogram = np.zeros(258, dtype=np.int64)
    for b in range(n_blocks):
        histogram[block_min[b]] += 1
    threshold, covered = 0, histogram[0]
    while covered < n_wanted:
        threshold += 1
        covered += histogram[threshold]
    # Counting sort of the entries <= threshold in the blocks that can hold them.
    counts = np.zeros(258, dtype=np.int64)
    for b in range(n_blocks):
        if block_min[b] <= threshold:
            for j in range(b * BLOCK, min(b * BLOCK + BLOCK, n_codes)):
                if distances[j] <= threshold:
                    counts[distances[j] + 1] += 1
    for d in range(1, 258):
        counts[d] += counts[d - 1]  # counts[d] = first output slot of distance d
    written = 0
    for b in range(n_blocks):
        if block_min[b] <= threshold:
            for j in range(b * BLOCK, min(b * BLOCK + BLOCK, n_codes)):
                d = distances[j]
                if d <= threshold:
                    slot = counts[d]
                    counts[d] += 1
                    if slot < n_wanted:
                        out_rows[slot] = j
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

"""Compiled exhaustive Hamming scan with top-n selection (numba). Imported lazily.

Codes are 256 bits, stored transposed as (4, capacity) uint64 words, so that the scan's
inner loop runs over entries with one vector lane per entry (vector popcount: AVX-512
VPOPCNTQ, or a nibble table on AVX2). Selection avoids sorting a million distances: the
scan writes each distance as one byte and keeps each block's minimum; a histogram of the
block minima gives a threshold T under which at least n entries lie (each block whose
minimum is <= T holds one); only those blocks' bytes are read again to collect their
entries <= T, and a counting sort over the few candidates returns the n nearest in
distance order. Also the re-rank's kernels: full-code Hamming distances of gathered rows
and exact float distances of VLAD rows read in place."""

from __future__ import annotations

import numpy as np
from numba import njit

from monoloc.server.vision._bits import popcount64 as _popcount64

BLOCK = 64


@njit(inline="always")
def _block_scan(q0, q1, q2, q3, codes_t, start, stop, distances):
    """Distances to codes start .. stop - 1 into distances[start:stop] and their minimum,
    both clamped at 255 (one byte per distance). The rows are sliced first so that the
    index is a loop counter from 0: LLVM then knows it is non-negative and uses plain
    vector loads. Indexing codes_t[w, start + j] directly keeps numba's negative-index
    wrap-around, which LLVM vectorises with gathers (several times slower)."""
    w0, w1 = codes_t[0, start:stop], codes_t[1, start:stop]
    w2, w3 = codes_t[2, start:stop], codes_t[3, start:stop]
    out = distances[start:stop]
    low = np.int32(1 << 20)
    for j in range(stop - start):
        d = np.int32(
            _popcount64(q0 ^ w0[j])
            + _popcount64(q1 ^ w1[j])
            + _popcount64(q2 ^ w2[j])
            + _popcount64(q3 ^ w3[j])
        )
        d = min(d, np.int32(255))
        out[j] = np.uint8(d)
        low = min(low, d)
    return low


@njit(cache=True, nogil=True, boundscheck=False)
def scan(query_words, codes_t, lo, hi, distances, block_min):
    """Hamming distances of query_words (4,) uint64 to codes_t[:, lo:hi] into
    distances[lo:hi] (uint8, 256 stored as 255) and each block of BLOCK codes' minimum
    (also capped at 255) into block_min[lo // BLOCK ...] (int32). ``lo`` must be a
    multiple of BLOCK; disjoint ranges may run in parallel. One byte per code keeps the
    writes to 1/32 of the reads, and lets :func:`select_nearest` revisit a block by
    reading one cache line."""
    q0, q1, q2, q3 = query_words[0], query_words[1], query_words[2], query_words[3]
    for b in range(lo // BLOCK, (hi + BLOCK - 1) // BLOCK):
        block_min[b] = _block_scan(
            q0, q1, q2, q3, codes_t, b * BLOCK, min(b * BLOCK + BLOCK, hi), distances
        )


@njit(cache=True, nogil=True, boundscheck=False)
def select_nearest(distances, block_min, n_codes, n_wanted, out_rows):
    """The ``n_wanted`` rows nearest to the query, given the distances and block minima
    written by :func:`scan` for rows 0 .. n_codes - 1, into out_rows (int64), nearest
    first (ties in row order). Returns how many were written (min(n_wanted, n_codes))."""
    n_blocks = (n_codes + BLOCK - 1) // BLOCK
    n_wanted = min(n_wanted, n_codes)
    if n_wanted <= 0:
        return 0
    histogram = np.zeros(258, dtype=np.int64)
    for b in range(n_blocks):
        histogram[block_min[b]] += 1
    # Smallest threshold with n_wanted blocks at or under it (each holds an entry <= it);
    # with fewer blocks than n_wanted, every block (threshold 255: every entry).
    threshold, covered = 0, histogram[0]
    while covered < n_wanted and threshold < 255:
        threshold += 1
        covered += histogram[threshold]
    # Gather the entries <= threshold of the blocks that can hold them, then a stable
    # counting sort by distance.
    kept = np.empty(min(covered * BLOCK, n_codes), dtype=np.int64)
    kept_d = np.empty(len(kept), dtype=np.int32)
    n_kept = 0
    counts = np.zeros(258, dtype=np.int64)
    for b in range(n_blocks):
        if block_min[b] <= threshold:
            start = b * BLOCK
            block = distances[start : min(start + BLOCK, n_codes)]
            for j in range(len(block)):
                d = np.int32(block[j])
                if d <= threshold:
                    kept[n_kept] = start + j
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
        code = codes_words[rows[k]]  # a row view: the word loop then needs no wrap-around
        d = np.uint64(0)
        for w in range(n_words):
            d += _popcount64(query_words[w] ^ code[w])
        out[k] = np.int32(d)


@njit(cache=True, nogil=True, boundscheck=False, fastmath=True)
def vlad_distances(query, vectors, rows, out):
    """Euclidean distances of query (D,) float64 to the float32 VLADs vectors[rows] into
    out (len(rows),) float64, accumulated in float64. Reading the rows in place avoids
    numpy's gathered copy, whose fresh pages cost more than the arithmetic (fastmath only
    reorders the sum, for vectorisation)."""
    n_dim = query.shape[0]
    for k in range(rows.shape[0]):
        vector = vectors[rows[k]]
        acc = 0.0
        for i in range(n_dim):
            d = np.float64(vector[i]) - query[i]
            acc += d * d
        out[k] = np.sqrt(acc)


@njit(cache=True, nogil=True, boundscheck=False, fastmath=True)
def nibble_sq_distances(q_even, q_odd, step, codes, rows, out):
    """Squared distances of a query to 4-bit codes codes[rows] ((N, D/2) uint8, value
    offset + step * nibble, low nibble first) into out (float32). The query comes with the
    offset subtracted, split into even and odd dimensions (q_even, q_odd: (D/2,) float32),
    so the loop over a code's bytes vectorises."""
    n_bytes = q_even.shape[0]
    for k in range(rows.shape[0]):
        code = codes[rows[k]]
        acc = np.float32(0.0)
        for j in range(n_bytes):
            byte = code[j]
            d0 = q_even[j] - step * np.float32(byte & 15)
            d1 = q_odd[j] - step * np.float32(byte >> 4)
            acc += d0 * d0 + d1 * d1
        out[k] = acc

"""Compiled Hamming matching kernel (numba). Imported lazily by monoloc.server.vision.matching.

One pass over the query x reference distance matrix, one query row at a time, never
storing the matrix: the row's distances go to a scratch buffer while their minimum is
taken. Rows whose minimum is above the bound are done: they can neither match nor
change any cross check (every candidate's distance is within the bound). The others are
reduced once more to the second-nearest distance and the nearest index, and fold into
the per-reference minimum and second minimum over queries that the cross check needs.

The popcount is written as the classic SWAR sequence, which LLVM recognises as ctpop;
with the reference descriptors transposed to (4, M) words (the kernel writes them into a
scratch buffer first, no numpy call per reference) the inner loop vectorises
(AVX2 nibble-table popcount on the dev box), ~0.8 ns per descriptor pair on one core.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from monoloc.server.vision._bits import FAR as _FAR
from monoloc.server.vision._bits import popcount64 as _popcount64


@njit(cache=True, boundscheck=False, nogil=True)
def match_rows(
    query_words,
    ref_words,
    max_bits,
    ratio,
    cross_check,
    ref_words_t,
    row,
    col_min1,
    col_min2,
    out_pairs,
    out_d,
):
    """Apply the match rule of monoloc.server.vision.matching to one query/reference pair.

    query_words (N, 4) and ref_words (M, 4) uint64 (descriptors as 64-bit words);
    ref_words_t (4, >= M) uint64 scratch receives the reference transposed (the layout
    the distance loop vectorises on); row, col_min1, col_min2 int32 scratch of >= M;
    out_pairs (>= N, 2) and out_d (>= N) int32 receive the matches [query, reference]
    (and scratch distances). Returns the number of matches K (rows [:K]), sorted by
    query index.
    """
    n, m = query_words.shape[0], ref_words.shape[0]
    for j in range(m):
        for w in range(4):
            ref_words_t[w, j] = ref_words[j, w]
    bound = np.int32(max_bits)
    for j in range(m):
        col_min1[j] = _FAR
        col_min2[j] = _FAR
    k = 0
    for i in range(n):
        a0, a1, a2, a3 = query_words[i, 0], query_words[i, 1], query_words[i, 2], query_words[i, 3]
        d1 = _FAR
        for j in range(m):
            d = np.int32(
                _popcount64(a0 ^ ref_words_t[0, j])
                + _popcount64(a1 ^ ref_words_t[1, j])
                + _popcount64(a2 ^ ref_words_t[2, j])
                + _popcount64(a3 ^ ref_words_t[3, j])
            )
            row[j] = d
            d1 = min(d1, d)
        if d1 > bound:
            continue
        # One vectorised pass (int32 throughout: an int64 or boolean accumulator here
        # doubles the kernel's time): the nearest distance above d1, the first and last
        # index at d1 (they differ iff d1 is tied), and the cross check's column state.
        d2 = _FAR
        first = _FAR
        last = np.int32(-1)
        for j in range(m):
            d = row[j]
            d2 = min(d2, d if d > d1 else _FAR)
            first = min(first, np.int32(j) if d == d1 else _FAR)
            last = max(last, np.int32(j) if d == d1 else np.int32(-1))
            if cross_check:
                c1 = col_min1[j]
                col_min2[j] = min(col_min2[j], max(c1, d))
                col_min1[j] = min(c1, d)
        # a tie makes the second-nearest distance d1, which fails d1 < ratio * d1
        if first != last or not (d1 < ratio * d2):
            continue
        out_pairs[k, 0] = i
        out_pairs[k, 1] = first
        out_d[k] = d1
        k += 1
    if not cross_check:
        return k
    kept = 0
    for t in range(k):
        # query i is reference j's unique nearest query: j's minimum over all queries is
        # i's distance and j's second minimum is larger
        j, d = out_pairs[t, 1], out_d[t]
        if col_min1[j] == d and col_min2[j] > d:
            out_pairs[kept, 0] = out_pairs[t, 0]
            out_pairs[kept, 1] = j
            kept += 1
    return kept

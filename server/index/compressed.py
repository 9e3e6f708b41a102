"""4-bit VLADs held in memory for the re-rank of a shortlist (the float VLADs stay on disk).

FAISS's uniform 4-bit scalar quantizer over a fixed range: 2048 values in 1024 bytes (an
8x cut from float32). The range is fixed, not trained, so that an entry added live to an
empty map is coded as one of a million-entry map is, and every replica codes alike. A
VLAD (docs/method.md section 4) is unit-norm with 64 intra-normalised rows: with all
rows non-zero each row's norm, and so each value, is at most 1/8 = ``VLAD_RANGE``;
a VLAD with empty rows may exceed it, and those values are clipped, which only blurs
the shortlist's order (the returned distances are exact, from the float VLADs; a range of
1/4 cost recall, docs/notebook/index-memory.md). Distances are asymmetric: the query
stays float.
"""

from __future__ import annotations

import functools

import numpy as np

from monoloc.server.vision.sizes import VLAD_DIM

VLAD_RANGE = 0.125
COMPRESSED_BYTES = VLAD_DIM // 2


@functools.cache
def vlad_quantizer():
    """FAISS ScalarQuantizer QT_4bit_uniform over [-VLAD_RANGE, VLAD_RANGE] (never
    changes: stored codes depend on it)."""
    import faiss

    sq = faiss.ScalarQuantizer(VLAD_DIM, faiss.ScalarQuantizer.QT_4bit_uniform)
    sq.trained.resize(2)  # uniform: (vmin, vdiff) shared by every dimension
    faiss.copy_array_to_vector(np.array([-VLAD_RANGE, 2 * VLAD_RANGE], np.float32), sq.trained)
    return sq


@functools.cache
def quantizer_levels() -> tuple[float, float]:
    """(offset, step): the value FAISS decodes nibble c to is offset + step * c. Read from
    FAISS's own decoder, dimension by dimension, so the distance kernel cannot drift."""
    codes = np.repeat(np.arange(16, dtype=np.uint8) * 0x11, COMPRESSED_BYTES).reshape(16, -1)
    levels = vlad_quantizer().decode(codes)
    if not np.allclose(levels, levels[:, :1], rtol=0, atol=1e-7):
        raise RuntimeError("FAISS's 4-bit uniform quantizer decodes dimensions differently")
    column = levels[:, 0].astype(np.float64)
    offset, step = column[0], (column[-1] - column[0]) / 15
    if not np.allclose(column, offset + step * np.arange(16), rtol=0, atol=1e-7):
        raise RuntimeError("FAISS's 4-bit uniform quantizer is not affine")
    return float(offset), float(step)


def compress_vlads(vlads: np.ndarray, chunk: int = 65536) -> np.ndarray:
    """(N, 2048) VLADs -> (N, 1024) uint8 4-bit codes (dimension 2j in byte j's low nibble,
    2j + 1 in its high nibble: FAISS's layout)."""
    values = np.asarray(vlads).reshape(-1, VLAD_DIM)
    sq = vlad_quantizer()
    out = np.empty((len(values), COMPRESSED_BYTES), dtype=np.uint8)
    for start in range(0, len(values), chunk):
        block = np.ascontiguousarray(values[start : start + chunk], dtype=np.float32)
        out[start : start + len(block)] = sq.compute_codes(block)
    return out


def compressed_sq_distances(query: np.ndarray, compressed: np.ndarray, rows: np.ndarray):
    """Squared L2 distances (R,) float32 of query (2048,) to the decoded 4-bit VLADs of
    rows ``rows`` (R,) of ``compressed`` (N, 1024) uint8."""
    from monoloc.server.index._scan_kernel import nibble_sq_distances

    offset, step = quantizer_levels()
    q = np.asarray(query, dtype=np.float32).reshape(VLAD_DIM) - np.float32(offset)
    q_even, q_odd = np.ascontiguousarray(q[0::2]), np.ascontiguousarray(q[1::2])
    out = np.empty(len(rows), dtype=np.float32)
    nibble_sq_distances(
        q_even, q_odd, np.float32(step), compressed, np.ascontiguousarray(rows, np.int64), out
    )
    return out

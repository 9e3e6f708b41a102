"""Compact binary codes of VLADs for the FAISS binary retrieval index (docs/method.md section 4).

The code of a VLAD v (2048 floats) is its sign pattern: bit i = 1 iff v[i] > 0 (zeros,
e.g. the rows of empty words, give 0). Bits are packed with ``np.packbits`` in its
default big-endian bit order: byte j holds v[8j] in its most significant bit (0x80)
down to v[8j+7] in its least significant bit. Hamming distance of two codes counts the
VLAD entries whose sign differs, and FAISS binary indexes only compare bytes, so the bit
order matters only for consistency (this module is the one place it is defined).

Why plain sign bits: measured on VLADs of 1500 random windows of 15 real photographs
(200 other windows as queries, default vocabulary; the data set of
tests/server/vision/test_vision_binary_code.py), recall@10 of a Hamming shortlist
re-ranked by exact float distance, against exact float search, for shortlists of
10 / 20 / 50 / 100: sign bits 0.903 / 0.998 / 0.999 / 0.999; a fixed seeded random
rotation (2048 x 2048 orthogonal) before the sign 0.931 / 1.000 / 1.000 / 1.000. The
retrieval index re-ranks a shortlist of 100, where the gain is 0.0005: not worth a 16 MB
matrix and a 4 M multiply-add product per VLAD.
"""

from __future__ import annotations

import numpy as np

from monoloc.core.errors import InvalidInputError


def vlad_binary_code(vlad: np.ndarray) -> np.ndarray:
    """Sign-bit code of one VLAD (D,) or a batch (N, D), D a multiple of 8 (2048 here).

    Returns (D/8,) or (N, D/8) uint8 (256 bytes for docs/method.md's 2048-d VLAD).
    """
    values = np.asarray(vlad)
    if values.ndim not in (1, 2) or values.shape[-1] % 8 != 0 or values.shape[-1] == 0:
        raise InvalidInputError(
            f"VLAD must be (D,) or (N, D) with D a multiple of 8, got shape {values.shape}"
        )
    if not np.issubdtype(values.dtype, np.floating) or not np.all(np.isfinite(values)):
        raise InvalidInputError("VLAD must be finite floats")
    return np.packbits(values > 0, axis=-1)


def hamming_distances(code: np.ndarray, codes: np.ndarray) -> np.ndarray:
    """Hamming distance of one code (B,) uint8 to each of (N, B) uint8 codes -> (N,) int64.

    A plain numpy reference (bit counts of the XOR); the retrieval index uses FAISS.
    """
    xor = np.bitwise_xor(np.asarray(codes, dtype=np.uint8), np.asarray(code, dtype=np.uint8))
    return np.bitwise_count(xor).sum(axis=-1, dtype=np.int64)

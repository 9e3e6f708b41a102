"""256-bit VLAD sketches and their exhaustive scan: the retrieval shortlist of large maps.

A sketch is the sign pattern of the VLAD projected on 256 fixed orthonormal directions
(seeded, the same for every map and every run): the Hamming distance of two sketches
estimates the angle between the two VLADs (sign random projection), with 8x fewer bits
than the 2048 sign bits of :func:`monoloc.server.vision.binary_code.vlad_binary_code`.

Why a scan and not a graph or inverted index: a query is about equally far from every
entry but its few true neighbours, so a greedy graph search has nothing to follow and
coarse cells split the neighbours (FAISS's binary HNSW and IVF are the baselines of
``bench/retrieval.py --baselines``). An exhaustive scan of 32-byte sketches reads 32 MB
per million entries, as fast as a bare read of them; selecting the nearest candidates
costs a fraction of that. Its candidates are re-ranked by the full 2048-bit codes and
finally by exact float distance.
"""

from __future__ import annotations

import functools
import threading

import numpy as np
from threadpoolctl import threadpool_limits

from monoloc.server.vision.sizes import VLAD_DIM

SKETCH_BITS = 256
SKETCH_BYTES = SKETCH_BITS // 8
_SKETCH_WORDS = SKETCH_BITS // 64
_PROJECTION_SEED = 20261122


@functools.cache
def sketch_projection() -> np.ndarray:
    """(2048, 256) float32 with orthonormal columns, from a fixed seed (never changes:
    stored sketches depend on it)."""
    rng = np.random.default_rng(_PROJECTION_SEED)
    # One BLAS thread: on a busy machine the threaded QR spends seconds handing work off
    # (this runs on a map's first load); the result is the same bit for bit.
    with threadpool_limits(1):
        q, _ = np.linalg.qr(rng.normal(size=(VLAD_DIM, SKETCH_BITS)))
    return np.ascontiguousarray(q, dtype=np.float32)


def vlad_sketch(vlads: np.ndarray, chunk: int = 65536) -> np.ndarray:
    """Sketches of VLADs: (2048,) -> (32,) uint8, or (N, 2048) -> (N, 32) uint8.

    Bit i (``np.packbits`` order) is 1 iff the VLAD's projection on direction i is > 0.
    """
    values = np.asarray(vlads, dtype=np.float32)
    single = values.ndim == 1
    values = values.reshape(-1, VLAD_DIM)
    projection = sketch_projection()
    out = np.empty((len(values), SKETCH_BYTES), dtype=np.uint8)
    for start in range(0, len(values), chunk):
        block = values[start : start + chunk] @ projection
        out[start : start + chunk] = np.packbits(block > 0, axis=1)
    return out[0] if single else out


class SketchTable:
    """The sketches of an index's rows, stored transposed ((4, capacity) uint64 words) for
    the scan. Row edits mirror the owning index's; the index's lock guards them."""

    def __init__(self) -> None:
        self._words_t = np.zeros((_SKETCH_WORDS, 0), dtype=np.uint64)
        # Per-thread scan output, reused: a fresh megabyte per query costs its page
        # faults, more than the selection that reads it.
        self._scratch = threading.local()

    def _distance_buffer(self, size: int) -> np.ndarray:
        buffer = getattr(self._scratch, "distances", None)
        if buffer is None or len(buffer) < size:
            buffer = np.empty(max(size, 1024), dtype=np.uint8)
            self._scratch.distances = buffer
        return buffer

    def reserve(self, capacity: int, size: int) -> None:
        if capacity <= self._words_t.shape[1]:
            return
        grown = np.zeros((_SKETCH_WORDS, capacity), dtype=np.uint64)
        grown[:, :size] = self._words_t[:, :size]
        self._words_t = grown

    def set_rows(self, start: int, sketches: np.ndarray) -> None:
        """Store (N, 32) uint8 sketches at rows start .. start + N - 1."""
        words = np.ascontiguousarray(sketches, dtype=np.uint8).view(np.uint64)
        self._words_t[:, start : start + len(words)] = words.T

    def move_row(self, dst: int, src: int) -> None:
        self._words_t[:, dst] = self._words_t[:, src]

    def rows(self, size: int) -> np.ndarray:
        """(size, 32) uint8 copy of the first ``size`` sketches (for persistence)."""
        return np.ascontiguousarray(self._words_t[:, :size].T).view(np.uint8)

    def nearest(self, sketch: np.ndarray, size: int, n_wanted: int):
        """Rows (<= n_wanted,) int64 of the sketches nearest to ``sketch`` (32,) uint8 among
        the first ``size`` rows, nearest first."""
        from monoloc.server.index._scan_kernel import BLOCK, scan, select_nearest

        query_words = np.ascontiguousarray(sketch, dtype=np.uint8).view(np.uint64)
        distances = self._distance_buffer(size)
        block_min = np.empty((size + BLOCK - 1) // BLOCK, dtype=np.int32)
        scan(query_words, self._words_t, 0, size, distances, block_min)
        out = np.empty(min(n_wanted, size), dtype=np.int64)
        written = select_nearest(distances, block_min, size, n_wanted, out)
        return out[:written]

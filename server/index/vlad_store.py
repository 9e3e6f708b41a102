"""The float VLADs of an index, read on demand: the exact distances of the final top k.

A store is a base array (the index file's memory-mapped float file, or an array the
caller hands over) and a delta of the VLADs added live since, in blocks of 256 rows
(2 MiB, each its own mapping: freed to the system when the delta is dropped). An index
row refers to its VLAD by a ref: ``r >= 0`` is base row r, ``r < 0`` delta slot -1 - r.
Removing a row only drops its ref (the slot is reclaimed when the index is next
persisted and its store becomes the new file).
"""

from __future__ import annotations

import numpy as np

from monoloc.server.vision.sizes import VLAD_DIM

_DELTA_BLOCK = 256


class VladStore:
    """Float32 VLADs by ref; the owning index's lock guards edits."""

    def __init__(self, base: np.ndarray | None = None) -> None:
        if base is None:
            base = np.zeros((0, VLAD_DIM), dtype=np.float32)
        if base.dtype != np.float32 or base.ndim != 2 or base.shape[1] != VLAD_DIM:
            raise ValueError(f"a VLAD store's base must be (N, {VLAD_DIM}) float32")
        self.base = base
        self._blocks: list[np.ndarray] = []
        self._delta_size = 0

    @property
    def delta_size(self) -> int:
        """Delta slots used (live adds since the base was written, removed ones included)."""
        return self._delta_size

    def append(self, vlads: np.ndarray) -> np.ndarray:
        """Keep (M, 2048) VLADs in the delta; returns their refs (M,) int64 (negative)."""
        vlads = np.asarray(vlads, dtype=np.float32).reshape(-1, VLAD_DIM)
        first = self._delta_size
        for offset in range(len(vlads)):
            slot = first + offset
            if slot // _DELTA_BLOCK == len(self._blocks):
                self._blocks.append(np.empty((_DELTA_BLOCK, VLAD_DIM), dtype=np.float32))
            self._blocks[slot // _DELTA_BLOCK][slot % _DELTA_BLOCK] = vlads[offset]
        self._delta_size += len(vlads)
        return -1 - np.arange(first, self._delta_size, dtype=np.int64)

    def gather(self, refs: np.ndarray) -> np.ndarray:
        """(R, 2048) float32 copies of the VLADs of ``refs`` (R,)."""
        refs = np.asarray(refs, dtype=np.int64).reshape(-1)
        out = np.empty((len(refs), VLAD_DIM), dtype=np.float32)
        in_base = refs >= 0
        if in_base.any():
            out[in_base] = self.base[refs[in_base]]
        for i in np.flatnonzero(~in_base):
            slot = -1 - int(refs[i])
            out[i] = self._blocks[slot // _DELTA_BLOCK][slot % _DELTA_BLOCK]
        return out

    def distances(self, query: np.ndarray, refs: np.ndarray) -> np.ndarray:
        """Exact L2 distances (R,) float64 of query (2048,) to the VLADs of ``refs``,
        accumulated in float64."""
        from monoloc.server.index._scan_kernel import vlad_distances

        vectors = self.gather(refs)
        out = np.empty(len(vectors), dtype=np.float64)
        rows = np.arange(len(vectors), dtype=np.int64)
        vlad_distances(np.asarray(query, dtype=np.float64), vectors, rows, out)
        return out

    def blocks(self, refs: np.ndarray, chunk: int = 4096):
        """The VLADs of ``refs`` in order, as (<= chunk, 2048) float32 arrays (for writing
        a file without holding all of them)."""
        refs = np.asarray(refs, dtype=np.int64)
        for start in range(0, len(refs), chunk):
            yield self.gather(refs[start : start + chunk])

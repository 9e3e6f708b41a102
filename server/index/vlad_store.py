"""The float VLADs of an index, read on demand: the exact distances of the final top k.

A store is a base (the index file's float file, read row by row with ``pread``: or an
array the caller hands over) and a delta of the VLADs added live since, in blocks of 256 rows
(2 MiB, each its own mapping: freed to the system when the delta is dropped). An index
row refers to its VLAD by a ref: ``r >= 0`` is base row r, ``r < 0`` delta slot -1 - r.
Removing a row only drops its ref (the slot is reclaimed when the index is next
persisted and its store becomes the new file).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from monoloc.server.vision.sizes import VLAD_DIM

_DELTA_BLOCK = 256
_ROW_BYTES = VLAD_DIM * 4


class VladFile:
    """The rows of a float32 ``.npy`` file of shape (N, 2048), read with ``pread``.

    Not a memory mapping: with the page cache's large folios one mapped row maps about a
    megabyte of its neighbours into the process, so a few hundred queries map the whole
    file (bench/footprint.py, docs/notebook/index-memory.md). Read, the rows stay in the
    page cache, which the kernel reclaims as it needs, and the replica's resident set
    holds none of them. The open descriptor keeps the file readable after it is replaced.
    """

    def __init__(self, path: Path, n_rows: int, data_offset: int) -> None:
        self.path = Path(path)
        self.shape = (int(n_rows), VLAD_DIM)
        self.dtype = np.dtype(np.float32)
        self.ndim = 2
        self._offset = int(data_offset)
        fd = os.open(self.path, os.O_RDONLY)
        if os.fstat(fd).st_size != self._offset + n_rows * _ROW_BYTES:
            os.close(fd)
            raise ValueError(f"{self.path} does not hold {n_rows} float32 VLADs")
        if hasattr(os, "posix_fadvise"):  # rows are read at random: no read-ahead
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_RANDOM)
        self._fd = fd

    def __len__(self) -> int:
        return self.shape[0]

    def __del__(self) -> None:
        fd = getattr(self, "_fd", None)
        if fd is not None:
            os.close(fd)
            self._fd = None

    def take(self, rows: np.ndarray, out: np.ndarray) -> None:
        """Read rows ``rows`` (R,) into out (R, 2048) float32."""
        view = out.reshape(len(rows), _ROW_BYTES // 4).view(np.uint8)
        rows = np.asarray(rows, dtype=np.int64).tolist()
        if any(not 0 <= row < self.shape[0] for row in rows):
            raise IndexError(f"rows outside {self.path}'s {self.shape[0]}")
        if len(rows) > 1 and hasattr(os, "posix_fadvise"):
            # Ask for every row first: rows not in the page cache are then read from
            # disk together, not one after the other (30 cold rows: p50 7.4 -> 0.7 ms).
            for row in rows:
                os.posix_fadvise(
                    self._fd, self._offset + row * _ROW_BYTES, _ROW_BYTES, os.POSIX_FADV_WILLNEED
                )
        for i, row in enumerate(rows):
            got = os.preadv(self._fd, [view[i]], self._offset + row * _ROW_BYTES)
            if got != _ROW_BYTES:
                raise OSError(f"{self.path}: short read of row {row}")

    def read_all(self) -> np.ndarray:
        """All rows (N, 2048) float32 (small maps; tests)."""
        out = np.empty(self.shape, dtype=np.float32)
        self.take(np.arange(len(self)), out)
        return out


class VladStore:
    """Float32 VLADs by ref; the owning index's lock guards edits."""

    def __init__(self, base: np.ndarray | VladFile | None = None) -> None:
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
        if in_base.all() and isinstance(self.base, VladFile):
            self.base.take(refs, out)
        elif in_base.any():
            if isinstance(self.base, VladFile):
                part = np.empty((int(in_base.sum()), VLAD_DIM), dtype=np.float32)
                self.base.take(refs[in_base], part)
                out[in_base] = part
            else:
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

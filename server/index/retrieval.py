"""Per-map retrieval index (docs/method.md section 4, monoloc's binary design).

A FAISS binary flat index over the entries' VLAD sign codes gives a Hamming shortlist;
large maps (from ``IndexConfig.scan_min_entries``) shortlist by an exhaustive scan of
256-bit sketches instead (monoloc.server.index.sketch says why), narrowed by the full
codes. The shortlist is re-ranked by 4-bit VLADs held in memory
(monoloc.server.index.compressed), and its ``k + exact_margin`` nearest by the exact L2
distance of the float VLADs, read on demand from the index file's float file
(monoloc.server.index.vlad_store): the distances returned are exact (they are
e_vlad, an input of the measurement model). Resident per entry: code 256 B, 4-bit VLAD
1 KiB, sketch 32 B, planar pose 24 B, id, VLAD ref and the id lookup (sorted ids) 32 B,
the planar grid 16 B.

With a planar prior only entries inside the radius (and heading window) compete: the
planar grid (monoloc.server.index.grid) gives the rows in the cells the prior's disk
overlaps and the prior's mask is applied to those only. Entries
are added and removed live; a readers-writer lock lets searches run concurrently but
never during an add or a remove (FAISS's rule).
"""

from __future__ import annotations

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.core.prior import RetrievalPrior
from monoloc.server.index.compressed import (
    COMPRESSED_BYTES,
    compress_vlads,
    compressed_sq_distances,
)
from monoloc.server.index.grid import PlanarGrid
from monoloc.server.index.rwlock import ReadWriteLock
from monoloc.server.index.sketch import SKETCH_BYTES, SketchTable, vlad_sketch
from monoloc.server.index.types import IndexConfig, SearchResult, empty_result
from monoloc.server.index.vlad_store import VladFile, VladStore
from monoloc.server.vision.sizes import CODE_BYTES, VLAD_DIM

__all__ = ["IndexConfig", "RetrievalIndex", "SearchResult"]

_CHUNK = 65536  # rows per block when building: bounded temporaries for huge maps


def _new_flat():
    import faiss

    return faiss.IndexBinaryIDMap2(faiss.IndexBinaryFlat(VLAD_DIM))


def _float32_rows(vlads):
    """``vlads`` as a VladFile (the index file's, kept) or an (N, 2048) float32
    C-contiguous array, without a copy when it is one (a memory mapping stays one)."""
    if isinstance(vlads, VladFile):
        return vlads
    if (
        isinstance(vlads, np.ndarray)
        and vlads.dtype == np.float32
        and vlads.ndim == 2
        and vlads.flags.c_contiguous
    ):
        return vlads.view(np.ndarray)  # numba's kernels take plain arrays, not np.memmap
    vlads = np.asarray(vlads).reshape(-1, VLAD_DIM)
    out = np.empty(vlads.shape, dtype=np.float32)
    for start in range(0, len(vlads), _CHUNK):
        out[start : start + _CHUNK] = vlads[start : start + _CHUNK]
    return out


class RetrievalIndex:
    """Live index of one map's entries. Thread-safe for concurrent search and edits."""

    def __init__(self, config: IndexConfig | None = None) -> None:
        self.config = config or IndexConfig()
        self._lock = ReadWriteLock()
        self._ids = np.zeros(0, dtype=np.int64)
        self._codes = np.zeros((0, CODE_BYTES), dtype=np.uint8)
        self._compressed = np.zeros((0, COMPRESSED_BYTES), dtype=np.uint8)
        self._poses = np.zeros((0, 3), dtype=np.float64)
        self._refs = np.zeros(0, dtype=np.int64)  # each row's VLAD in the store
        self._size = 0
        # id -> row without a dict (~100 B per entry): ids sorted, and their rows
        self._sorted_ids = np.zeros(0, dtype=np.int64)
        self._sorted_rows = np.zeros(0, dtype=np.int64)
        self._sketches = SketchTable()
        self._grid = PlanarGrid(self.config.prior_cell_m)
        self._store = VladStore()
        self._edits = 0  # counts adds and removes (persistence adopts a file only if unchanged)
        self._faiss = _new_flat()  # None once the sketches are the index ("scan")
        self._kind = "flat"

    # ---- construction -------------------------------------------------------------
    def __len__(self) -> int:
        return self._size

    @property
    def kind(self) -> str:
        """The shortlist: "flat" (FAISS's flat Hamming index) or "scan" (the sketches)."""
        return self._kind

    @property
    def unpersisted(self) -> int:
        """Float VLADs held in memory (added since the file was written, removed ones
        included): persisting the index moves them to its file."""
        return self._store.delta_size

    def entry_ids(self) -> np.ndarray:
        with self._lock.read():
            return self._ids[: self._size].copy()

    def __contains__(self, entry_id: int) -> bool:
        with self._lock.read():
            return bool(self._rows_of(np.array([int(entry_id)]))[0] >= 0)

    def _rows_of(self, ids: np.ndarray) -> np.ndarray:
        """Rows (M,) int64 of entry ids (M,), -1 where absent."""
        ids = np.asarray(ids, dtype=np.int64)
        n = len(self._sorted_ids)
        if n == 0:
            return np.full(len(ids), -1, dtype=np.int64)
        pos = np.minimum(np.searchsorted(self._sorted_ids, ids), n - 1)
        return np.where(self._sorted_ids[pos] == ids, self._sorted_rows[pos], -1)

    # ---- edits --------------------------------------------------------------------
    def _reserve(self, extra: int) -> None:
        need = self._size + extra
        if need <= len(self._ids):
            return
        capacity = max(need, 2 * len(self._ids), 64)

        def grow(arr: np.ndarray) -> np.ndarray:
            out = np.zeros((capacity, *arr.shape[1:]), dtype=arr.dtype)
            out[: self._size] = arr[: self._size]
            return out

        self._ids, self._codes, self._refs = grow(self._ids), grow(self._codes), grow(self._refs)
        self._compressed, self._poses = grow(self._compressed), grow(self._poses)
        self._sketches.reserve(capacity, self._size)

    def add(
        self, entry_ids: np.ndarray, codes: np.ndarray, vlads: np.ndarray, poses_world: np.ndarray
    ) -> None:
        """Add entries: ids (N,) int64, codes (N, 256) uint8, VLADs (N, 2048), poses (N, 3).

        Ids already present are replaced (an entry re-computed with a new vocabulary). The
        float VLADs stay in memory until the index is next persisted.
        """
        ids = np.asarray(entry_ids, dtype=np.int64).reshape(-1)
        codes = np.ascontiguousarray(codes, dtype=np.uint8).reshape(len(ids), CODE_BYTES)
        vlads = np.asarray(vlads, dtype=np.float32).reshape(len(ids), VLAD_DIM)
        poses = np.asarray(poses_world, dtype=np.float64).reshape(len(ids), 3)
        if len(np.unique(ids)) != len(ids):
            raise InvalidInputError("duplicate entry ids in one add")
        compressed, sketches = compress_vlads(vlads), vlad_sketch(vlads)
        with self._lock.write():
            self._remove_locked(ids)
            self._reserve(len(ids))
            rows = slice(self._size, self._size + len(ids))
            self._ids[rows], self._codes[rows], self._poses[rows] = ids, codes, poses
            self._compressed[rows] = compressed
            self._refs[rows] = self._store.append(vlads)
            self._sketches.set_rows(self._size, sketches)
            self._grid.add_rows(self._size, poses)
            order = np.argsort(ids, kind="stable")
            at = np.searchsorted(self._sorted_ids, ids[order])
            new_rows = np.arange(self._size, self._size + len(ids), dtype=np.int64)[order]
            self._sorted_ids = np.insert(self._sorted_ids, at, ids[order])
            self._sorted_rows = np.insert(self._sorted_rows, at, new_rows)
            self._size += len(ids)
            self._edits += 1
            if self._kind == "flat":
                if self._size >= self.config.scan_min_entries:
                    self._faiss, self._kind = None, "scan"  # the sketches are the index
                else:
                    self._faiss.add_with_ids(codes, ids)

    def remove(self, entry_ids) -> int:
        """Remove entries by id; unknown ids are ignored. Returns how many were removed."""
        wanted = np.unique(np.asarray(entry_ids, dtype=np.int64).reshape(-1))
        with self._lock.write():
            return self._remove_locked(wanted)

    def _remove_locked(self, wanted: np.ndarray) -> int:
        import faiss

        rows = self._rows_of(wanted)
        present = wanted[rows >= 0]
        rows = rows[rows >= 0]
        if len(rows) == 0:
            return 0
        keep = ~np.isin(self._sorted_ids, present)
        self._sorted_ids, self._sorted_rows = self._sorted_ids[keep], self._sorted_rows[keep]
        # Compact: move the last live rows into the holes (a VLAD moves by its ref).
        origin: dict[int, int] = {}  # row now -> the row it held before this removal
        for row in np.sort(rows)[::-1].tolist():
            last = self._size - 1
            if row != last:
                origin[row] = origin.pop(last, last)
                self._ids[row], self._codes[row] = self._ids[last], self._codes[last]
                self._compressed[row], self._poses[row] = self._compressed[last], self._poses[last]
                self._refs[row] = self._refs[last]
                self._sketches.move_row(row, last)
                pos = np.searchsorted(self._sorted_ids, self._ids[row])
                self._sorted_rows[pos] = row
            self._size -= 1
        self._grid.remove_rows(rows, {old: new for new, old in origin.items()})
        self._edits += 1
        if self._faiss is not None:  # a map that shrinks under the size keeps its scan
            self._faiss.remove_ids(faiss.IDSelectorBatch(present))
        return len(rows)

    def _build_shortlist(self) -> None:
        """The shortlist index of the rows held: the sketches alone from
        ``scan_min_entries`` on, else a flat FAISS index of the codes."""
        if self._size >= self.config.scan_min_entries:
            self._faiss, self._kind = None, "scan"
            return
        self._faiss, self._kind = _new_flat(), "flat"
        if self._size:
            codes = np.ascontiguousarray(self._codes[: self._size])
            self._faiss.add_with_ids(codes, self._ids[: self._size])

    # ---- search -------------------------------------------------------------------
    def search(
        self,
        vlad_query: np.ndarray,
        code_query: np.ndarray,
        k: int = 10,
        prior: RetrievalPrior | None = None,
    ) -> SearchResult:
        """Top-k entries by exact VLAD distance, shortlisted by Hamming distance of codes
        and by the 4-bit VLADs."""
        if k < 1:
            raise InvalidInputError(f"k must be >= 1, got {k}")
        query = np.asarray(vlad_query, dtype=np.float32).reshape(VLAD_DIM)
        code = np.ascontiguousarray(code_query, dtype=np.uint8).reshape(1, CODE_BYTES)
        with self._lock.read():
            if self._size == 0:
                return empty_result()
            sketch = vlad_sketch(query) if self._kind == "scan" else None
            if prior is None:
                size = max(self.config.shortlist_size, k)
                rows = self._shortlist_rows(code, sketch, size, cap=k)
            else:
                rows = self._prior_rows(code, sketch, k, prior)
            return self._rerank(query, rows, k)

    def _hamming_nearest(self, code: np.ndarray, rows: np.ndarray, size: int) -> np.ndarray:
        """The ``size`` rows of ``rows`` nearest by full-code Hamming distance."""
        from monoloc.server.index._scan_kernel import hamming_rows

        if len(rows) <= size:
            return rows
        rows = np.ascontiguousarray(rows, dtype=np.int64)
        distances = np.empty(len(rows), dtype=np.int32)
        code_words = np.ascontiguousarray(code[0]).view(np.uint64)
        hamming_rows(code_words, self._codes.view(np.uint64), rows, distances)
        return rows[np.argsort(distances, kind="stable")[:size]]

    def _scan_rows(self, code: np.ndarray, sketch: np.ndarray, size: int) -> np.ndarray:
        """Top ``size`` rows by full-code Hamming among the sketch scan's candidates."""
        n_candidates = max(self.config.scan_candidates, 4 * size)
        rows = self._sketches.nearest(sketch, self._size, n_candidates)
        return self._hamming_nearest(code, rows, size)

    def _shortlist_rows(self, code: np.ndarray, sketch, size: int, cap: int | None = None):
        """Up to ``size`` rows nearest by Hamming distance. With ``cap`` (the k wanted),
        the scan returns at most ``scan_shortlist`` rows, but never fewer than ``cap``; a
        prior search passes no cap and widens past the shortlist."""
        if self._kind == "scan":
            if cap is not None:
                size = min(size, max(self.config.scan_shortlist, cap))
            return self._scan_rows(code, sketch, size)
        _, found = self._faiss.search(code, min(size, self._size))
        rows = self._rows_of(found[0][found[0] >= 0])
        return rows[rows >= 0]

    def _prior_rows(self, code: np.ndarray, sketch, k: int, prior: RetrievalPrior) -> np.ndarray:
        """At most ``shortlist_size`` (or k) rows inside the prior, nearest by Hamming."""
        size = max(self.config.shortlist_size, k)
        inside = self._inside_rows(prior)
        if len(inside) <= self.config.prior_hamming_max:
            return self._hamming_nearest(code, inside, size)
        # Many candidates: widen the Hamming shortlist until enough fall inside the prior.
        inside_set = np.zeros(self._size, dtype=bool)
        inside_set[inside] = True
        wanted = size
        while True:
            rows = self._shortlist_rows(code, sketch, wanted)
            rows = rows[inside_set[rows]]
            if len(rows) >= self.config.shortlist_size or wanted >= self._size:
                return rows[:size]
            wanted *= 4

    def _inside_rows(self, prior: RetrievalPrior) -> np.ndarray:
        """Rows (ascending int64) inside the prior: ``flatnonzero(prior.mask(poses))``,
        the mask applied only to the rows of the grid cells the prior's disk overlaps."""
        rows = self._grid.candidates(prior, max_rows=self._size // 2)
        if rows is None:  # the prior covers much of the map: the plain mask is cheaper
            return np.flatnonzero(prior.mask(self._poses[: self._size]))
        rows.sort()
        return rows[prior.mask(self._poses[rows])]

    def _rerank(self, query: np.ndarray, rows: np.ndarray, k: int) -> SearchResult:
        """The k nearest of ``rows`` by exact distance, among the ``k + exact_margin``
        nearest by the 4-bit VLADs."""
        if len(rows) == 0:
            return empty_result()
        rows = np.ascontiguousarray(rows, dtype=np.int64)
        n_exact = k + self.config.exact_margin
        if len(rows) > n_exact:
            approx = compressed_sq_distances(query, self._compressed, rows)
            rows = rows[np.argsort(approx, kind="stable")[:n_exact]]
        dist = self._store.distances(query, self._refs[rows])
        order = np.argsort(dist, kind="stable")[:k]
        return SearchResult(self._ids[rows[order]].copy(), dist[order].astype(np.float32))

    # ---- snapshot (for persistence) ---------------------------------------------------
    def poses_world(self) -> np.ndarray:
        """A copy (N, 3) of the entries' planar poses, in row order."""
        with self._lock.read():
            return self._poses[: self._size].copy()

    def vlads_at(self, rows: np.ndarray) -> np.ndarray:
        """The float32 VLADs (R, 2048) of rows ``rows`` (R,) (indices into
        :meth:`poses_world`), read from the store (the index file) without the rest."""
        rows = np.asarray(rows, dtype=np.intp)
        with self._lock.read():
            if len(rows) and (rows.min() < 0 or rows.max() >= self._size):
                raise InvalidInputError(f"rows outside the index's {self._size} entries")
            return self._store.gather(self._refs[rows])

    def snapshot(self) -> dict[str, np.ndarray]:
        """Copies of the live arrays: ids, codes, float32 vlads (read from the store: N x 8
        KiB, for small maps), compressed (4-bit) vlads, poses, sketches."""
        with self._lock.read():
            n = self._size
            return {
                "ids": self._ids[:n].copy(),
                "codes": self._codes[:n].copy(),
                "vlads": self._store.gather(self._refs[:n]),
                "compressed": self._compressed[:n].copy(),
                "poses": self._poses[:n].copy(),
                "sketches": self._sketches.rows(n),
            }

    def persist_state(self):
        """(arrays, vlad blocks, edits) for writing a file: copies of the small arrays, an
        iterator over the float VLADs in row order (read after the lock is released: the
        store's rows never change once written) and the edit count to pass back to
        :meth:`adopt_vlads` once the file is written."""
        with self._lock.read():
            n = self._size
            arrays = {
                "ids": self._ids[:n].copy(),
                "codes": self._codes[:n].copy(),
                "compressed": self._compressed[:n].copy(),
                "poses": self._poses[:n].copy(),
                "sketches": self._sketches.rows(n),
            }
            return arrays, self._store.blocks(self._refs[:n].copy()), self._edits

    def adopt_vlads(self, vlads, edits: int) -> bool:
        """Read the float VLADs from ``vlads`` (the VladFile just written, in row order)
        and drop the in-memory delta, unless the index was edited since
        :meth:`persist_state` gave ``edits``. Returns whether it was adopted."""
        base = _float32_rows(vlads)
        with self._lock.write():
            if edits != self._edits or len(base) != self._size:
                return False
            self._store = VladStore(base)
            self._refs[: self._size] = np.arange(self._size, dtype=np.int64)
            return True

    @classmethod
    def from_arrays(
        cls,
        ids,
        codes,
        vlads,
        poses,
        config: IndexConfig | None = None,
        sketches=None,
        compressed=None,
    ) -> RetrievalIndex:
        """Build an index from arrays. ``vlads`` (N, 2048) is read in place, not copied,
        when it is float32 and C-contiguous, or a VladFile (the index file's): the caller
        must not change it afterwards. ``sketches`` (N, 32) and ``compressed`` (N, 1024) uint8 (as
        ``snapshot`` gives them) skip recomputing them from the VLADs."""
        index = cls(config)
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        if len(np.unique(ids)) != len(ids):
            raise InvalidInputError("duplicate entry ids")
        n = len(ids)
        base = _float32_rows(vlads)
        if base.shape != (n, VLAD_DIM):
            raise InvalidInputError(f"vlads must be ({n}, {VLAD_DIM})")
        index._reserve(n)
        index._ids[:n] = ids
        index._codes[:n] = np.asarray(codes, dtype=np.uint8).reshape(n, CODE_BYTES)
        index._poses[:n] = np.asarray(poses, dtype=np.float64).reshape(n, 3)
        for name, given, width in (
            ("sketches", sketches, SKETCH_BYTES),
            ("compressed", compressed, COMPRESSED_BYTES),
        ):
            if given is not None and np.shape(given) != (n, width):
                raise InvalidInputError(f"{name} must be ({n}, {width}) uint8")
        if compressed is not None:
            index._compressed[:n] = compressed
        if sketches is not None:
            index._sketches.set_rows(0, np.asarray(sketches, dtype=np.uint8))
        recompute = compressed is None or sketches is None
        source = base.read_all() if recompute and isinstance(base, VladFile) else base
        for start in range(0, n if recompute else 0, _CHUNK):
            block = source[start : start + _CHUNK]
            if compressed is None:
                index._compressed[start : start + len(block)] = compress_vlads(block)
            if sketches is None:
                index._sketches.set_rows(start, vlad_sketch(block))
        index._store = VladStore(base)
        index._refs[:n] = np.arange(n, dtype=np.int64)
        order = np.argsort(ids, kind="stable")
        index._sorted_ids, index._sorted_rows = ids[order], order.astype(np.int64)
        index._grid.build(index._poses[:n])
        index._size = n
        index._build_shortlist()
        return index

"""Lab baseline: the retrieval index as it was until 2026-12-02, float VLADs resident.

monoloc.server.index.retrieval before issue 52's memory work, kept so that bench/footprint.py
and bench/retrieval.py measure the product beside it in the same run: every entry's
float32 VLAD (8 KiB) in memory, an id -> row dict, the scan's 20-row shortlist and a
prior's up to 20,000 inside rows re-ranked exactly. Not used by the product.

Its design, as it was documented:

A FAISS binary flat index over the entries' VLAD sign codes gives a Hamming shortlist;
the shortlist is re-ranked by the exact L2 distance of the float VLADs. Large maps (from
``IndexConfig.scan_min_entries``) shortlist by an exhaustive scan of 256-bit sketches
instead (monoloc.server.index.sketch says why), re-ranked by the full codes and then
exactly. With a planar prior only entries inside the radius (and heading window)
compete. Entries are added and removed live; a readers-writer lock lets searches run
concurrently but never during an add or a remove (FAISS's rule).
"""

from __future__ import annotations

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.core.prior import RetrievalPrior
from monoloc.server.index.rwlock import ReadWriteLock
from monoloc.server.index.sketch import SKETCH_BYTES, SketchTable, vlad_sketch
from monoloc.server.index.types import IndexConfig, SearchResult, empty_result
from monoloc.server.vision.sizes import CODE_BYTES, VLAD_DIM

__all__ = ["FloatRetrievalIndex", "TODAY"]

TODAY = IndexConfig(scan_shortlist=20)  # the settings of 2026-12-01
PRIOR_EXACT_MAX = 20_000  # up to this many candidates, re-rank all exactly


def _new_flat():
    import faiss

    return faiss.IndexBinaryIDMap2(faiss.IndexBinaryFlat(VLAD_DIM))


class FloatRetrievalIndex:
    """Live index of one map's entries. Thread-safe for concurrent search and edits."""

    def __init__(self, config: IndexConfig | None = None) -> None:
        self.config = config or TODAY
        self._lock = ReadWriteLock()
        self._ids = np.zeros(0, dtype=np.int64)
        self._codes = np.zeros((0, CODE_BYTES), dtype=np.uint8)
        self._vlads = np.zeros((0, VLAD_DIM), dtype=np.float32)
        self._poses = np.zeros((0, 3), dtype=np.float64)
        self._size = 0
        self._row_of_id: dict[int, int] = {}
        self._sketches = SketchTable()
        self._faiss = _new_flat()  # None once the sketches are the index ("scan")
        self._kind = "flat"

    # ---- construction -------------------------------------------------------------
    def __len__(self) -> int:
        return self._size

    @property
    def kind(self) -> str:
        """The shortlist: "flat" (FAISS's flat Hamming index) or "scan" (the sketches)."""
        return self._kind

    def entry_ids(self) -> np.ndarray:
        with self._lock.read():
            return self._ids[: self._size].copy()

    def __contains__(self, entry_id: int) -> bool:
        return int(entry_id) in self._row_of_id

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

        self._ids, self._codes = grow(self._ids), grow(self._codes)
        self._vlads, self._poses = grow(self._vlads), grow(self._poses)
        self._sketches.reserve(capacity, self._size)

    def add(
        self, entry_ids: np.ndarray, codes: np.ndarray, vlads: np.ndarray, poses_world: np.ndarray
    ) -> None:
        """Add entries: ids (N,) int64, codes (N, 256) uint8, VLADs (N, 2048), poses (N, 3).

        Ids already present are replaced (an entry re-computed with a new vocabulary).
        """
        ids = np.asarray(entry_ids, dtype=np.int64).reshape(-1)
        codes = np.ascontiguousarray(codes, dtype=np.uint8).reshape(len(ids), CODE_BYTES)
        vlads = np.asarray(vlads, dtype=np.float32).reshape(len(ids), VLAD_DIM)
        poses = np.asarray(poses_world, dtype=np.float64).reshape(len(ids), 3)
        if len(np.unique(ids)) != len(ids):
            raise InvalidInputError("duplicate entry ids in one add")
        present = [int(i) for i in ids if int(i) in self._row_of_id]
        if present:
            self.remove(present)
        with self._lock.write():
            self._reserve(len(ids))
            rows = slice(self._size, self._size + len(ids))
            self._ids[rows], self._codes[rows], self._poses[rows] = ids, codes, poses
            self._vlads[rows] = vlads
            self._sketches.set_rows(self._size, vlad_sketch(vlads))
            for offset, entry_id in enumerate(ids):
                self._row_of_id[int(entry_id)] = self._size + offset
            self._size += len(ids)
            if self._kind == "flat":
                if self._size >= self.config.scan_min_entries:
                    self._faiss, self._kind = None, "scan"  # the sketches are the index
                else:
                    self._faiss.add_with_ids(codes, ids)

    def remove(self, entry_ids) -> int:
        """Remove entries by id; unknown ids are ignored. Returns how many were removed."""
        import faiss

        wanted = [int(i) for i in np.asarray(entry_ids, dtype=np.int64).reshape(-1)]
        with self._lock.write():
            rows = [self._row_of_id.pop(i) for i in wanted if i in self._row_of_id]
            if not rows:
                return 0
            # Compact: move the last live rows into the holes.
            for row in sorted(rows, reverse=True):
                last = self._size - 1
                if row != last:
                    moved_id = int(self._ids[last])
                    self._ids[row], self._codes[row] = self._ids[last], self._codes[last]
                    self._vlads[row], self._poses[row] = self._vlads[last], self._poses[last]
                    self._sketches.move_row(row, last)
                    self._row_of_id[moved_id] = row
                self._size -= 1
            if self._faiss is not None:  # a map that shrinks under the size keeps its scan
                self._faiss.remove_ids(faiss.IDSelectorBatch(np.asarray(wanted, dtype=np.int64)))
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
        """Top-k entries by exact VLAD distance, shortlisted by Hamming distance of codes."""
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

    def _scan_rows(self, code: np.ndarray, sketch: np.ndarray, size: int) -> np.ndarray:
        """Top ``size`` rows by full-code Hamming among the sketch scan's candidates."""
        from monoloc.server.index._scan_kernel import hamming_rows

        n_candidates = max(self.config.scan_candidates, 4 * size)
        rows = self._sketches.nearest(sketch, self._size, n_candidates)
        if len(rows) <= size:
            return rows
        distances = np.empty(len(rows), dtype=np.int32)
        code_words = np.ascontiguousarray(code[0]).view(np.uint64)
        hamming_rows(code_words, self._codes.view(np.uint64), rows, distances)
        return rows[np.argsort(distances, kind="stable")[:size]]

    def _shortlist_rows(self, code: np.ndarray, sketch, size: int, cap: int | None = None):
        """Up to ``size`` rows nearest by Hamming distance. With ``cap`` (the k wanted),
        the scan returns at most ``scan_shortlist`` rows, but never fewer than ``cap``; a
        prior search passes no cap and widens past the shortlist."""
        if self._kind == "scan":
            if cap is not None:
                size = min(size, max(self.config.scan_shortlist, cap))
            return self._scan_rows(code, sketch, size)
        _, found = self._faiss.search(code, min(size, self._size))
        row_of_id = self._row_of_id
        rows = [row_of_id[i] for i in found[0].tolist() if i >= 0]
        return np.array(rows, dtype=np.int64)

    def _prior_rows(self, code: np.ndarray, sketch, k: int, prior: RetrievalPrior) -> np.ndarray:
        inside = np.flatnonzero(prior.mask(self._poses[: self._size]))
        if len(inside) <= PRIOR_EXACT_MAX:
            return inside
        # Many candidates: widen the Hamming shortlist until enough fall inside the prior.
        inside_set = np.zeros(self._size, dtype=bool)
        inside_set[inside] = True
        size = max(self.config.shortlist_size, k)
        while True:
            rows = self._shortlist_rows(code, sketch, size)
            rows = rows[inside_set[rows]]
            if len(rows) >= self.config.shortlist_size or size >= self._size:
                return rows
            size *= 4

    def _rerank(self, query: np.ndarray, rows: np.ndarray, k: int) -> SearchResult:
        from monoloc.server.index._scan_kernel import vlad_distances

        if len(rows) == 0:
            return empty_result()
        rows = np.ascontiguousarray(rows, dtype=np.int64)
        dist = np.empty(len(rows), dtype=np.float64)
        vlad_distances(query.astype(np.float64), self._vlads, rows, dist)
        order = np.argsort(dist, kind="stable")[:k]
        return SearchResult(self._ids[rows[order]].copy(), dist[order].astype(np.float32))

    # ---- snapshot (for persistence) ---------------------------------------------------
    def poses_world(self) -> np.ndarray:
        """A copy (N, 3) of the entries' planar poses, in row order."""
        with self._lock.read():
            return self._poses[: self._size].copy()

    def vlads_at(self, rows: np.ndarray) -> np.ndarray:
        """The float32 VLADs (R, 2048) of rows ``rows`` (R,) (indices into
        :meth:`poses_world`), without copying the whole index."""
        rows = np.asarray(rows, dtype=np.intp)
        with self._lock.read():
            if len(rows) and (rows.min() < 0 or rows.max() >= self._size):
                raise InvalidInputError(f"rows outside the index's {self._size} entries")
            return self._vlads[rows].copy()

    def snapshot(self) -> dict[str, np.ndarray]:
        """Copies of the live arrays: ids, codes, float32 vlads, poses, sketches."""
        with self._lock.read():
            n = self._size
            return {
                "ids": self._ids[:n].copy(),
                "codes": self._codes[:n].copy(),
                "vlads": self._vlads[:n].copy(),
                "poses": self._poses[:n].copy(),
                "sketches": self._sketches.rows(n),
            }

    @classmethod
    def from_arrays(
        cls,
        ids,
        codes,
        vlads,
        poses,
        config: IndexConfig | None = None,
        sketches=None,
    ) -> FloatRetrievalIndex:
        """Build an index from arrays; ``sketches`` (N, 32) uint8 (as ``snapshot`` gives
        them) skip recomputing them from the VLADs."""
        index = cls(config)
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        if len(np.unique(ids)) != len(ids):
            raise InvalidInputError("duplicate entry ids")
        n = len(ids)
        index._reserve(n)
        index._ids[:n] = ids
        index._codes[:n] = np.asarray(codes, dtype=np.uint8).reshape(n, CODE_BYTES)
        index._poses[:n] = np.asarray(poses, dtype=np.float64).reshape(n, 3)
        vlads = np.asarray(vlads).reshape(n, VLAD_DIM)
        if sketches is not None:
            sketches = np.asarray(sketches, dtype=np.uint8)
            if sketches.shape != (n, SKETCH_BYTES):
                raise InvalidInputError(f"sketches must be ({n}, {SKETCH_BYTES}) uint8")
            index._sketches.set_rows(0, sketches)
        for start in range(0, n, 65536):  # chunked: bounded temporaries for huge maps
            stop = min(n, start + 65536)
            block = vlads[start:stop].astype(np.float32)
            index._vlads[start:stop] = block
            if sketches is None:
                index._sketches.set_rows(start, vlad_sketch(block))
        index._size = n
        index._row_of_id = {int(i): row for row, i in enumerate(ids)}
        index._build_shortlist()
        return index

"""The rows of an index bucketed by planar grid cell: where a prior's rows are found.

A prior's mask over every entry's pose costs O(N) per query (about 6 ms at a million
entries); the cells its disk overlaps hold the rows it can contain. The grid keeps every
row's cell key in one array sorted by key (y cell major, then x cell), with the rows
beside: one grid row of cells is one contiguous key range, so a disk is found with two
binary searches per grid row it spans. The caller applies the exact mask to the rows
found (``RetrievalPrior.mask``): the rows inside are exactly the brute-force mask's.

Cells are squares of ``cell_m`` metres in the world frame. Non-finite poses (never inside
a prior) are filed in cell (0, 0); cell indices are clamped to +-2^30 (about 17e6 km at
16 m cells), which keeps the keys in int64 and the comparisons monotone.
"""

from __future__ import annotations

import math

import numpy as np

from monoloc.core.prior import RetrievalPrior

_CELL_LIMIT = 1 << 30
_X_SPAN = 1 << 31  # x cells per key row: key = (iy + 2^30) * 2^31 + (ix + 2^30)
# A prior spanning more grid rows than this is answered by the plain mask (cost O(N)
# either way, and the searches would cost more than the mask).
MAX_GRID_ROWS = 4096


def _cells(values_m: np.ndarray, cell_m: float) -> np.ndarray:
    """Cell indices (N,) int64 of coordinates (N,) float64, clamped; non-finite -> 0."""
    scaled = np.floor(np.asarray(values_m, dtype=np.float64) / cell_m)
    scaled = np.nan_to_num(scaled, nan=0.0, posinf=_CELL_LIMIT, neginf=-_CELL_LIMIT)
    return np.clip(scaled, -_CELL_LIMIT, _CELL_LIMIT).astype(np.int64)


def _keys(ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
    return (iy + _CELL_LIMIT) * _X_SPAN + (ix + _CELL_LIMIT)


def cell_keys(poses_world: np.ndarray, cell_m: float) -> np.ndarray:
    """Cell keys (N,) int64 of planar poses (N, 3) (x_m, y_m, yaw_rad)."""
    poses = np.asarray(poses_world, dtype=np.float64).reshape(-1, 3)
    return _keys(_cells(poses[:, 0], cell_m), _cells(poses[:, 1], cell_m))


class PlanarGrid:
    """Rows (int64) of an index sorted by their pose's cell key. Edits mirror the owning
    index's (its lock guards them); 16 B per row."""

    def __init__(self, cell_m: float) -> None:
        if not (math.isfinite(cell_m) and cell_m > 0):
            raise ValueError(f"cell_m must be finite and > 0, got {cell_m}")
        self.cell_m = float(cell_m)
        self._keys = np.zeros(0, dtype=np.int64)
        self._rows = np.zeros(0, dtype=np.int64)

    def __len__(self) -> int:
        return len(self._rows)

    @property
    def nbytes(self) -> int:
        return self._keys.nbytes + self._rows.nbytes

    def build(self, poses_world: np.ndarray) -> None:
        """File rows 0 .. N - 1 of poses (N, 3), replacing what was held."""
        keys = cell_keys(poses_world, self.cell_m)
        order = np.argsort(keys, kind="stable")
        self._keys, self._rows = keys[order], order.astype(np.int64)

    def add_rows(self, start: int, poses_world: np.ndarray) -> None:
        """File new rows start .. start + M - 1 of poses (M, 3)."""
        keys = cell_keys(poses_world, self.cell_m)
        order = np.argsort(keys, kind="stable")
        at = np.searchsorted(self._keys, keys[order], side="right")
        self._keys = np.insert(self._keys, at, keys[order])
        self._rows = np.insert(self._rows, at, start + order.astype(np.int64))

    def remove_rows(self, removed: np.ndarray, moved_to: dict[int, int]) -> None:
        """Drop rows ``removed`` and renumber the rows that moved into the holes
        (``moved_to``: old row -> new row), both in the numbering before the removal."""
        keep = ~np.isin(self._rows, np.asarray(removed, dtype=np.int64))
        self._keys, self._rows = self._keys[keep], self._rows[keep]
        if not moved_to:
            return
        old = np.fromiter(moved_to.keys(), dtype=np.int64, count=len(moved_to))
        new = np.fromiter(moved_to.values(), dtype=np.int64, count=len(moved_to))
        order = np.argsort(old)
        old, new = old[order], new[order]
        at = np.flatnonzero(np.isin(self._rows, old))
        self._rows[at] = new[np.searchsorted(old, self._rows[at])]

    def candidates(self, prior: RetrievalPrior, max_rows: int | None = None):
        """Rows (unsorted int64) in the cells the prior's disk overlaps: a superset of the
        rows inside it. None when the disk spans more than MAX_GRID_ROWS grid rows or
        would give more than ``max_rows`` candidates (the plain mask is cheaper then)."""
        c = self.cell_m
        # Padded against rounding: a pose the mask finds inside is never outside the
        # padded disk (its coordinates' rounding is far below this margin).
        margin = 1e-6 + 1e-9 * (abs(prior.x_m) + abs(prior.y_m) + prior.radius_m)
        r = prior.radius_m + margin
        iy0, iy1 = _cells(np.array([prior.y_m - r, prior.y_m + r]), c)
        if iy1 - iy0 + 1 > MAX_GRID_ROWS:
            return None
        iy = np.arange(iy0, iy1 + 1, dtype=np.int64)
        # The disk's half-width over each grid row: at the row's nearest y to the centre.
        dy = np.maximum(0.0, np.maximum(iy * c - prior.y_m, prior.y_m - (iy + 1) * c))
        half = np.sqrt(np.maximum(r * r - dy * dy, 0.0)) + margin
        lo = _keys(_cells(prior.x_m - half, c), iy)
        hi = _keys(_cells(prior.x_m + half, c), iy)
        starts = np.searchsorted(self._keys, lo, side="left")
        stops = np.searchsorted(self._keys, hi, side="right")
        counts = stops - starts
        total = int(counts.sum())
        if max_rows is not None and total > max_rows:
            return None
        # Positions of every range, concatenated: start of its range + offset inside it.
        offsets = np.arange(total, dtype=np.int64)
        offsets += np.repeat(starts - (np.cumsum(counts) - counts), counts)
        return self._rows[offsets]

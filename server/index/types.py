"""Settings, prior and result types of the retrieval index (monoloc.server.index.retrieval)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import wrap_angle


@dataclass(frozen=True)
class RetrievalPrior:
    """Only entries within ``radius_m`` of (x_m, y_m), and within ``yaw_tolerance_rad`` of
    ``yaw_rad`` when both are given, compete."""

    x_m: float
    y_m: float
    radius_m: float
    yaw_rad: float | None = None
    yaw_tolerance_rad: float | None = None

    def __post_init__(self) -> None:
        values = [self.x_m, self.y_m, self.radius_m]
        if self.yaw_rad is not None:
            values.append(self.yaw_rad)
        if self.yaw_tolerance_rad is not None:
            values.append(self.yaw_tolerance_rad)
        if not all(math.isfinite(v) for v in values) or self.radius_m <= 0:
            raise InvalidInputError(f"invalid retrieval prior {self}")

    def mask(self, poses_world: np.ndarray) -> np.ndarray:
        """Boolean (N,) of entries (planar poses (N, 3)) inside the prior."""
        d2 = (poses_world[:, 0] - self.x_m) ** 2 + (poses_world[:, 1] - self.y_m) ** 2
        inside = d2 <= self.radius_m**2
        if self.yaw_rad is not None and self.yaw_tolerance_rad is not None:
            inside &= np.abs(wrap_angle(poses_world[:, 2] - self.yaw_rad)) <= self.yaw_tolerance_rad
        return inside


@dataclass(frozen=True)
class IndexConfig:
    """Retrieval settings. ``shortlist_size`` Hamming candidates are re-ranked exactly."""

    shortlist_size: int = 400
    # From this size on another shortlist replaces FAISS's flat index: "scan" (default:
    # exhaustive sketch scan, see monoloc.server.index.sketch), FAISS's binary "hnsw" or "ivf".
    large_kind: str = "scan"
    scan_candidates: int = 1000  # sketch-nearest rows re-ranked by the full codes
    scan_shortlist: int = 20  # full-code-nearest of those re-ranked exactly
    scan_threads: int = 1  # 2 splits each scan over two cores (memory bound: ~10 % faster)
    ivf_min_entries: int = 50_000
    hnsw_m: int = 32
    hnsw_ef_construction: int = 40
    hnsw_ef_search: int = 128
    hnsw_shortlist: int = 100  # HNSW returns this many for the exact re-rank
    # HNSW cannot delete: removed entries are tombstones, filtered from results, until
    # they exceed this share of the index, which is then rebuilt.
    hnsw_max_tombstones: float = 0.2
    ivf_lists_per_sqrt: float = 2.0  # nlist = this * sqrt(N)
    ivf_train_per_list: int = 40  # training sample = this * nlist codes (k-means cost)
    ivf_nprobe: int = 32
    prior_exact_max: int = 20_000  # up to this many candidates, re-rank all exactly
    # Re-rank vectors: "float32" is exact; "int8" (per-entry scale, step ~1e-3 of the
    # largest component) quarters the memory of very large maps at a negligible ranking cost.
    vector_dtype: str = "float32"

    def __post_init__(self) -> None:
        if self.large_kind not in ("scan", "hnsw", "ivf"):
            raise InvalidInputError(f"large_kind must be scan, hnsw or ivf, not {self.large_kind}")
        if self.scan_candidates < 1 or self.scan_shortlist < 1 or self.scan_threads not in (1, 2):
            raise InvalidInputError(
                "scan_candidates and scan_shortlist must be >= 1 and scan_threads 1 or 2"
            )
        if self.vector_dtype not in ("float32", "int8"):
            raise InvalidInputError(
                f"vector_dtype must be float32 or int8, not {self.vector_dtype}"
            )


@dataclass(frozen=True)
class SearchResult:
    """Top-k entries, best first: ids (k,) int64 and VLAD L2 distances (k,) float32."""

    entry_ids: np.ndarray
    distances: np.ndarray


def empty_result() -> SearchResult:
    return SearchResult(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.float32))

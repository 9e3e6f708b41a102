"""Settings and result types of the retrieval index (monoloc.server.index.retrieval); its
prior is ``monoloc.core.prior.RetrievalPrior``, shared with the vehicle."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monoloc.core.errors import InvalidInputError


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

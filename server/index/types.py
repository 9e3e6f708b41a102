"""Settings and result types of the retrieval index (monoloc.server.index.retrieval); its
prior is ``monoloc.core.prior.RetrievalPrior``, shared with the vehicle."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from monoloc.core.errors import InvalidInputError


@dataclass(frozen=True)
class IndexConfig:
    """Retrieval settings. A Hamming shortlist is re-ranked by the 4-bit VLADs held in
    memory; the ``k + exact_margin`` nearest of those by the float VLADs read on demand,
    whose exact distances are returned."""

    shortlist_size: int = 400
    # From this size on the exhaustive sketch scan (monoloc.server.index.sketch) replaces
    # FAISS's flat index: its cost per query no longer grows with the full codes' bytes.
    scan_min_entries: int = 50_000
    scan_candidates: int = 1000  # sketch-nearest rows re-ranked by the full codes
    scan_shortlist: int = 100  # full-code-nearest of those re-ranked by the 4-bit VLADs
    # Inside a prior: up to this many candidates are ranked by Hamming distance directly;
    # more widen the map-wide shortlist until enough fall inside.
    prior_hamming_max: int = 20_000
    # The planar grid that finds a prior's rows (monoloc.server.index.grid): square cells
    # of this side. Vehicle priors are 8-60 m in radius (client.tracking): a 60 m disk
    # spans about 8 x 8 cells, a 8 m one 2 x 2.
    prior_cell_m: float = 16.0
    exact_margin: int = 20  # float VLADs read per query: k + exact_margin

    def __post_init__(self) -> None:
        if self.scan_candidates < 1 or self.scan_shortlist < 1:
            raise InvalidInputError("scan_candidates and scan_shortlist must be >= 1")
        if self.exact_margin < 0:
            raise InvalidInputError("exact_margin must be >= 0")
        if not (math.isfinite(self.prior_cell_m) and self.prior_cell_m > 0):
            raise InvalidInputError("prior_cell_m must be finite and > 0")


@dataclass(frozen=True)
class SearchResult:
    """Top-k entries, best first: ids (k,) int64 and VLAD L2 distances (k,) float32."""

    entry_ids: np.ndarray
    distances: np.ndarray


def empty_result() -> SearchResult:
    return SearchResult(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.float32))

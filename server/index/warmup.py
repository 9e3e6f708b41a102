"""Load (or compile) the retrieval kernels before serving: the exact re-rank and the
sketch scan are numba kernels, and the first call in a process would otherwise pay for
loading them inside a query. Counterpart of ``monoloc.server.vision.warmup``."""

from __future__ import annotations

import numpy as np

from monoloc.core.prior import RetrievalPrior
from monoloc.server.index.retrieval import IndexConfig, RetrievalIndex
from monoloc.server.vision.binary_code import vlad_binary_code
from monoloc.server.vision.sizes import VLAD_DIM


def warm_up() -> None:
    """One search of a tiny flat index and one of a tiny scan index (the kind large maps
    use), with and without a prior."""
    rng = np.random.default_rng(0)
    vlads = rng.normal(size=(8, VLAD_DIM)).astype(np.float32)
    vlads /= np.linalg.norm(vlads, axis=1, keepdims=True)
    codes = np.stack([vlad_binary_code(v) for v in vlads])
    poses = np.zeros((8, 3))
    poses[:, 0] = np.arange(8.0)
    prior = RetrievalPrior(x_m=2.0, y_m=0.0, radius_m=3.0)
    # The scan kind with a shortlist of 2 re-ranks its 8 candidates by the full codes too;
    # no exact margin: the 4-bit re-rank runs on 8 entries.
    flat, scan = (
        IndexConfig(exact_margin=0),
        IndexConfig(scan_min_entries=4, scan_shortlist=2, exact_margin=0),
    )
    for config in (flat, scan):
        index = RetrievalIndex(config)
        index.add(np.arange(8), codes, vlads, poses)
        for with_prior in (None, prior):
            index.search(vlads[0], codes[0], 1, with_prior)

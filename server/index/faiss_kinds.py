"""FAISS binary indexes over 2048-bit VLAD codes: the flat index of small maps and the
selectable approximate kinds (IVF, HNSW) of large ones."""

from __future__ import annotations

import math

import numpy as np

from monoloc.server.index.types import IndexConfig
from monoloc.server.vision.sizes import VLAD_DIM


def new_flat():
    import faiss

    return faiss.IndexBinaryIDMap2(faiss.IndexBinaryFlat(VLAD_DIM))


def new_ivf(codes: np.ndarray, config: IndexConfig):
    """IVF over ``codes`` (trained on a sample of them); nlist grows with sqrt(N)."""
    import faiss

    nlist = max(16, int(config.ivf_lists_per_sqrt * math.sqrt(len(codes))))
    quantizer = faiss.IndexBinaryFlat(VLAD_DIM)
    ivf = faiss.IndexBinaryIVF(quantizer, VLAD_DIM, nlist)  # the wrapper keeps quantizer
    n_train = config.ivf_train_per_list * nlist
    train = codes if len(codes) <= n_train else codes[:: len(codes) // n_train]
    ivf.train(np.ascontiguousarray(train))
    ivf.nprobe = config.ivf_nprobe
    return ivf


def new_hnsw(config: IndexConfig):
    import faiss

    hnsw = faiss.IndexBinaryHNSW(VLAD_DIM, config.hnsw_m)
    hnsw.hnsw.efConstruction = config.hnsw_ef_construction
    hnsw.hnsw.efSearch = config.hnsw_ef_search
    return faiss.IndexBinaryIDMap2(hnsw)


def configure(index, kind: str, config: IndexConfig) -> None:
    """Apply the search-time settings of ``config`` to a (loaded) FAISS index."""
    import faiss

    if kind == "ivf":
        index.nprobe = config.ivf_nprobe
    elif kind == "hnsw":
        inner = faiss.downcast_IndexBinary(index.index)
        inner.hnsw.efSearch = max(config.hnsw_ef_search, config.hnsw_shortlist)

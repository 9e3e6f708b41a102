"""Retrieval index: FAISS binary shortlist over VLAD codes, exact float re-rank."""

from monoloc.server.index.retrieval import RetrievalIndex, SearchResult

__all__ = ["RetrievalIndex", "SearchResult"]

"""Thread counts of the libraries a query runs in (OpenCV, FAISS, BLAS): one place for the
server and the one-shot CLI, so that both time a query the same way."""

from __future__ import annotations

from monoloc.server.settings import Settings


def limit_threads(settings: Settings):
    """Set OpenCV/FAISS/BLAS thread counts; returns the threadpoolctl limiter to undo.

    Why the CLI needs it too: with FAISS's default OpenMP pool, one binary search of a
    100-entry map took ~30 ms on the 2-core dev VM under load instead of ~0.1 ms.
    """
    import cv2
    import faiss
    from threadpoolctl import threadpool_limits

    cv2.setNumThreads(settings.cv_threads)
    faiss.omp_set_num_threads(settings.faiss_threads)
    return threadpool_limits(limits=1)

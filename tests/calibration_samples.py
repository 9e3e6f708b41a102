"""Synthetic calibration samples (server/calibrate.CalibrationSamples) for the fit's unit
tests: one hypothesis a query, its pose errors and covariances given, the retrieval and
match figures drawn plausibly from the test's rng (shared by the bias and floor tests)."""

from __future__ import annotations

import numpy as np


def synthetic_samples(
    rng: np.random.Generator,
    truth: np.ndarray,
    hypothesis: np.ndarray,
    entry_offsets_m: np.ndarray,
    pose_covariances: np.ndarray,
):
    """Samples of N queries: ``truth`` and ``hypothesis`` (N, 3) world x, y, heading, each
    query's entry at ``entry_offsets_m`` (N, 2) from the truth, ``pose_covariances``
    (N, 3, 3) the hypotheses' PnP covariances; none of them a joint pose."""
    from monoloc.server.calibrate import CalibrationSamples

    n = len(truth)
    return CalibrationSamples(
        truth=truth.tolist(),
        hypothesis=hypothesis.tolist(),
        e_vlad=rng.normal(1.2, 0.05, n).tolist(),
        e_vlad_best=rng.normal(1.15, 0.05, n).tolist(),
        entry_pose=np.column_stack([truth[:, :2] + entry_offsets_m, truth[:, 2]]).tolist(),
        n_inliers=rng.integers(20, 200, n).tolist(),
        error_px=rng.uniform(0.5, 2.0, n).tolist(),
        joint=[False] * n,
        pose_covariance=np.asarray(pose_covariances).reshape(n, 9).tolist(),
        query_index=list(range(n)),
        entry_index=list(range(n)),
        neighbour_e_vlad=rng.normal(1.1, 0.05, 50).tolist(),
        n_hypotheses=n,
        n_queries_with_hypotheses=n,
        n_queries=n,
    )

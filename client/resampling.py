"""Resampling helpers for the particle filter: small pure functions."""

from __future__ import annotations

import numpy as np


def normalise_log_weights(log_weights: np.ndarray) -> np.ndarray:
    """Weights (P,) summing to 1 from unnormalised log weights (P,)."""
    shifted = np.exp(log_weights - np.max(log_weights))
    return shifted / shifted.sum()


def effective_sample_size(weights: np.ndarray) -> float:
    """1 / sum(w^2) for normalised weights (P,)."""
    return float(1.0 / np.sum(np.square(weights)))


def systematic_resample(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices (P,) int64 drawn by systematic resampling: one uniform offset, P strata."""
    n = len(weights)
    positions = (rng.uniform() + np.arange(n)) / n
    cumulative = np.cumsum(weights)
    cumulative[-1] = 1.0  # guard against round-off leaving the last stratum uncovered
    return np.searchsorted(cumulative, positions, side="left")

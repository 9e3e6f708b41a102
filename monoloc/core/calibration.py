"""Maximum-likelihood fit of the measurement model (METHOD.md section 7, calibration).

The server gathers the error samples from a training run; the fit itself is pure math
and lives here so the vehicle and the server share one definition.
"""

from __future__ import annotations

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import wrap_angle
from monoloc.core.measurement import MeasurementModel


def pose_errors(truth_world: np.ndarray, hypotheses_world: np.ndarray) -> np.ndarray:
    """e_i = z_q - z_i with wrapped heading. (N, 3) and (N, 3) -> (N, 3)."""
    e = np.asarray(truth_world, dtype=np.float64) - np.asarray(hypotheses_world, np.float64)
    e[:, 2] = wrap_angle(e[:, 2])
    return e


def retrieval_vectors(
    e_vlad: np.ndarray, entry_pose_world: np.ndarray, truth_world: np.ndarray
) -> np.ndarray:
    """[e_vlad_i, X_i - X_q, Y_i - Y_q, wrap(psi_i - psi_q)] per sample: (N, 4)."""
    entry = np.asarray(entry_pose_world, dtype=np.float64)
    truth = np.asarray(truth_world, dtype=np.float64)
    out = np.empty((len(entry), 4))
    out[:, 0] = e_vlad
    out[:, 1:3] = entry[:, :2] - truth[:, :2]
    out[:, 3] = wrap_angle(entry[:, 2] - truth[:, 2])
    return out


def fit_gaussian(
    samples: np.ndarray, unbiased: bool, floor_std: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Mean (D,) and covariance (D, D) of samples (N, D).

    ``unbiased`` divides by N - 1 about the mean; otherwise the paper's mean(e e^T), which
    is the second moment about zero. A diagonal floor (floor_std^2) keeps the covariance
    well conditioned when a component barely varies.
    """
    if samples.ndim != 2 or len(samples) < samples.shape[1] + 1:
        raise InvalidInputError(
            f"need at least {samples.shape[-1] + 1} error samples to calibrate, got {len(samples)}"
        )
    mean = samples.mean(axis=0)
    if unbiased:
        centred = samples - mean
        cov = centred.T @ centred / (len(samples) - 1)
    else:
        cov = samples.T @ samples / len(samples)
    cov = 0.5 * (cov + cov.T) + np.diag(np.square(floor_std))
    return mean, cov


def fit_measurement_model(
    pose_error_samples: np.ndarray,
    retrieval_samples: np.ndarray,
    unbiased: bool = True,
    outlier_log_density: float | None = -16.0,
    source: str = "calibrated",
) -> MeasurementModel:
    """mu1, Sigma1 from pose errors (N, 3); mu2, Sigma2 from retrieval vectors (M, 4).

    monoloc's default is the unbiased covariance about the mean (``unbiased=True``);
    ``unbiased=False`` reproduces the paper's formula mean(e e^T).
    """
    if not np.all(np.isfinite(pose_error_samples)) or not np.all(np.isfinite(retrieval_samples)):
        raise InvalidInputError("calibration samples contain NaN or infinite values")
    mu1, Sigma1 = fit_gaussian(
        np.asarray(pose_error_samples, np.float64), unbiased, np.array([0.01, 0.01, 1e-3])
    )
    mu2, Sigma2 = fit_gaussian(
        np.asarray(retrieval_samples, np.float64), unbiased, np.array([0.01, 0.05, 0.05, 1e-3])
    )
    return MeasurementModel(
        mu1=mu1,
        Sigma1=Sigma1,
        mu2=mu2,
        Sigma2=Sigma2,
        outlier_log_density=outlier_log_density,
        source=source,
    )

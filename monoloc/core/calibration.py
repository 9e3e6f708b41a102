"""Maximum-likelihood fit of the measurement model (docs/method.md section 7, calibration).

The server gathers the error samples from a training run; the fit itself is pure math
and lives here so the vehicle and the server share one definition.
"""

from __future__ import annotations

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import wrap_angle
from monoloc.core.measurement import (
    DEFAULT_RELATIVE_VLAD,
    DEFAULT_RETRIEVAL_FRAME,
    MeasurementModel,
    PnpCovarianceModel,
    QualityModel,
    RetrievalFrame,
    quality_features,
)


def pose_errors(truth_world: np.ndarray, hypotheses_world: np.ndarray) -> np.ndarray:
    """e_i = z_q - z_i with wrapped heading. (N, 3) and (N, 3) -> (N, 3)."""
    e = np.asarray(truth_world, dtype=np.float64) - np.asarray(hypotheses_world, np.float64)
    e[:, 2] = wrap_angle(e[:, 2])
    return e


def retrieval_vectors(
    e_vlad: np.ndarray,
    entry_pose_world: np.ndarray,
    truth_world: np.ndarray,
    frame: RetrievalFrame = DEFAULT_RETRIEVAL_FRAME,
) -> np.ndarray:
    """[e_vlad_i, X_i - X_q, Y_i - Y_q, wrap(psi_i - psi_q)] per sample: (N, 4); with
    ``frame="vehicle"`` the offset is turned into the query's frame (along, across its
    heading psi_q; see monoloc.core.measurement)."""
    entry = np.asarray(entry_pose_world, dtype=np.float64)
    truth = np.asarray(truth_world, dtype=np.float64)
    out = np.empty((len(entry), 4))
    out[:, 0] = e_vlad
    offset = entry[:, :2] - truth[:, :2]
    if frame == "vehicle":
        cos_q, sin_q = np.cos(truth[:, 2]), np.sin(truth[:, 2])
        offset = np.stack(
            [
                cos_q * offset[:, 0] + sin_q * offset[:, 1],
                cos_q * offset[:, 1] - sin_q * offset[:, 0],
            ],
            axis=1,
        )
    elif frame != "world":
        raise InvalidInputError(f"retrieval frame must be 'world' or 'vehicle', got {frame!r}")
    out[:, 1:3] = offset
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


# Smallest spread Sigma2 may have (1 sigma): of the entry's offset in any direction (m)
# and of its heading difference (rad). A minimum, not an addition: the training run's
# queries all come from the map's own drive, so a run along one straight street would
# otherwise give a Sigma2 too narrow for any later drive; one that turns keeps its own.
RETRIEVAL_MIN_STD_M = 1.0
RETRIEVAL_MIN_STD_RAD = 0.05


def _clamp_retrieval_spread(Sigma2: np.ndarray) -> np.ndarray:
    """Sigma2 (4, 4) with its offset block's eigenvalues and its heading variance raised
    to the minimum spreads (raising either adds a positive semidefinite matrix)."""
    out = Sigma2.copy()
    values, vectors = np.linalg.eigh(out[1:3, 1:3])
    raised = np.maximum(values, RETRIEVAL_MIN_STD_M**2) - values
    out[1:3, 1:3] += (vectors * raised) @ vectors.T
    out[3, 3] = max(out[3, 3], RETRIEVAL_MIN_STD_RAD**2)
    return 0.5 * (out + out.T)


# The paper covariance's tail (``MeasurementModel.tail_weight`` / ``tail_scale``): set,
# not fitted, because a training run never shows the errors it stands for (its queries
# meet the nearest entries of their own drive). A tail ten times as wide with a 30 %
# share keeps a wrong hypothesis a few decimetres off from dragging the particle cloud
# onto itself, while the right ones weigh as before (measured: docs/notebook/measurement-model.md).
# 0 switches it off (the paper's single Gaussian).
PAPER_TAIL_WEIGHT = 0.3
PAPER_TAIL_SCALE = 10.0


def fit_relative_vlad(relative_e_vlad: np.ndarray, unbiased: bool = True) -> tuple[float, float]:
    """(mean, std) of the relative VLAD distances (N,) (e_vlad minus its frame's best;
    ``MeasurementModel.relative_vlad``), the std at least ``RELATIVE_VLAD_MIN_STD``; the
    documented default when fewer than two samples are given."""
    values = np.asarray(relative_e_vlad, dtype=np.float64).reshape(-1)
    values = values[np.isfinite(values)]
    if len(values) < 2:
        return DEFAULT_RELATIVE_VLAD
    std = float(values.std(ddof=1 if unbiased else 0))
    return float(values.mean()), max(std, RELATIVE_VLAD_MIN_STD)


# A frame's best hypothesis has relative distance 0 by construction; a floor keeps a
# training run of near-identical distances from making the term a spike.
RELATIVE_VLAD_MIN_STD = 0.01


def fit_measurement_model(
    pose_error_samples: np.ndarray,
    retrieval_samples: np.ndarray,
    unbiased: bool = True,
    outlier_log_density: float | None = -16.0,
    source: str = "calibrated",
    retrieval_frame: RetrievalFrame = DEFAULT_RETRIEVAL_FRAME,
    tail_weight: float = PAPER_TAIL_WEIGHT,
    tail_scale: float = PAPER_TAIL_SCALE,
) -> MeasurementModel:
    """mu1, Sigma1 from pose errors (N, 3); mu2, Sigma2 from retrieval vectors (M, 4)
    computed in ``retrieval_frame`` (:func:`retrieval_vectors`).

    monoloc's default is the unbiased covariance about the mean (``unbiased=True``);
    ``unbiased=False`` reproduces the paper's formula mean(e e^T). Sigma2's spread is
    at least ``RETRIEVAL_MIN_STD_M`` / ``RETRIEVAL_MIN_STD_RAD``. The pose error's tail
    (``tail_weight``, ``tail_scale``) is set, not fitted (see ``PAPER_TAIL_WEIGHT``);
    ``tail_weight=0`` gives the paper's single Gaussian.
    """
    if not np.all(np.isfinite(pose_error_samples)) or not np.all(np.isfinite(retrieval_samples)):
        raise InvalidInputError("calibration samples contain NaN or infinite values")
    mu1, Sigma1 = fit_gaussian(
        np.asarray(pose_error_samples, np.float64), unbiased, np.array([0.01, 0.01, 1e-3])
    )
    mu2, Sigma2 = fit_gaussian(
        np.asarray(retrieval_samples, np.float64), unbiased, np.array([0.01, 0.05, 0.05, 1e-3])
    )
    Sigma2 = _clamp_retrieval_spread(Sigma2)
    return MeasurementModel(
        mu1=mu1,
        Sigma1=Sigma1,
        mu2=mu2,
        Sigma2=Sigma2,
        outlier_log_density=outlier_log_density,
        source=source,
        retrieval_frame=retrieval_frame,
        tail_weight=tail_weight,
        tail_scale=tail_scale,
    )


def fit_quality_model(
    pose_error_samples: np.ndarray,
    n_inliers: np.ndarray,
    reprojection_error_px: np.ndarray,
    joint: np.ndarray,
    n_ref: float = 100.0,
    error_ref_px: float = 1.0,
    iterations: int = 100,
    tolerance: float = 1e-9,
    heavy_tail: bool = True,
) -> QualityModel:
    """Maximum-likelihood fit of the quality-aware model (monoloc.core.measurement) to
    pose errors e_i (N, 3) = truth - hypothesis with their quality features (N,) each.

    The likelihood is prod_i N(e_i; mu1, s_i Sigma1), log s_i = beta . x_i. Coordinate
    ascent, each step exact or convex: for fixed beta, mu1 is the 1/s_i-weighted mean and
    Sigma1 the weighted covariance (closed form); for fixed (mu1, Sigma1), beta minimises
    sum_i 0.5 m_i exp(-beta . x_i) + 1.5 beta . x_i (m_i the Mahalanobis distance under
    Sigma1), a convex function, by damped Newton steps. A feature that never varies
    (e.g. no joint sample) keeps a zero slope. Sigma1 gets the same diagonal floor as
    the paper's fit.

    With ``heavy_tail`` the model's tail (``QualityModel.tail_weight`` / ``tail_scale``)
    is fitted too, by EM started from the Gaussian fit: the E step gives each sample's
    probability r_i of the tail; the M step is the same coordinate ascent with each
    sample's Mahalanobis distance weighted by (1 - r_i) + r_i / tail_scale^2, then
    tail_scale^2 = sum r_i m_i / s_i / (3 sum r_i) and tail_weight = mean r_i. The tail is
    kept only if it improves the likelihood.
    """
    e = np.asarray(pose_error_samples, dtype=np.float64)
    x = quality_features(n_inliers, reprojection_error_px, joint, n_ref, error_ref_px)
    if e.ndim != 2 or e.shape[1] != 3 or len(x) != len(e):
        raise InvalidInputError(
            f"need pose errors (N, 3) and N quality features, got {e.shape} and {len(x)}"
        )
    if len(e) < 10:
        raise InvalidInputError(f"need at least 10 samples to fit the quality model, got {len(e)}")
    if not (np.all(np.isfinite(e)) and np.all(np.isfinite(x))):
        raise InvalidInputError("quality calibration samples contain NaN or infinite values")
    free = np.array([np.ptp(x[:, k]) > 1e-9 for k in range(3)])
    floor = np.diag(np.square([0.01, 0.01, 1e-3]))
    beta = np.zeros(3)
    previous = np.inf
    for _ in range(iterations):
        w = np.exp(-x @ beta)
        mu1 = (w[:, None] * e).sum(axis=0) / w.sum()
        centred = e - mu1
        Sigma1 = (w[:, None, None] * centred[:, :, None] * centred[:, None, :]).mean(axis=0)
        Sigma1 = 0.5 * (Sigma1 + Sigma1.T) + floor
        maha = np.einsum("ij,ij->i", centred @ np.linalg.inv(Sigma1), centred)
        beta = _fit_log_scale(x[:, free], maha, beta[free], free)
        nll = _quality_nll(centred, x @ beta, Sigma1)
        if previous - nll < tolerance * max(1.0, abs(nll)):
            break
        previous = nll
    gaussian = QualityModel(
        mu1=mu1, Sigma1=Sigma1, beta=beta, n_ref=n_ref, error_ref_px=error_ref_px
    )
    if not heavy_tail:
        return gaussian
    tailed = _fit_tail(e, x, free, gaussian, floor, iterations, tolerance)
    return tailed if _mixture_nll(e, x, tailed) < _mixture_nll(e, x, gaussian) else gaussian


def _fit_tail(
    e: np.ndarray,
    x: np.ndarray,
    free: np.ndarray,
    start: QualityModel,
    floor: np.ndarray,
    iterations: int,
    tolerance: float,
) -> QualityModel:
    """EM for the heavy-tailed quality model (see :func:`fit_quality_model`), from the
    Gaussian fit with its covariance split into a core a quarter as wide and a tail."""
    mu1, beta = start.mu1, start.beta
    Sigma1 = start.Sigma1 / 4.0
    weight, k2 = 0.1, 16.0
    previous = np.inf
    for _ in range(iterations * 5):
        centred = e - mu1
        scaled = np.einsum("ij,ij->i", centred @ np.linalg.inv(Sigma1), centred) * np.exp(
            -(x @ beta)
        )
        # E step: probability that each sample came from the tail
        log_core = np.log1p(-weight) - 0.5 * scaled
        log_tail = np.log(weight) - 1.5 * np.log(k2) - 0.5 * scaled / k2
        r = 1.0 / (1.0 + np.exp(np.clip(log_core - log_tail, -700.0, 700.0)))
        a = (1.0 - r) + r / k2
        # M step
        w = a * np.exp(-(x @ beta))
        mu1 = (w[:, None] * e).sum(axis=0) / w.sum()
        centred = e - mu1
        Sigma1 = (w[:, None, None] * centred[:, :, None] * centred[:, None, :]).mean(axis=0)
        Sigma1 = 0.5 * (Sigma1 + Sigma1.T) + floor
        maha = np.einsum("ij,ij->i", centred @ np.linalg.inv(Sigma1), centred)
        beta = _fit_log_scale(x[:, free], maha * a, beta[free], free)
        scaled = maha * np.exp(-(x @ beta))
        k2 = max(float((r * scaled).sum() / max(3.0 * r.sum(), 1e-12)), 1.0 + 1e-6)
        weight = float(np.clip(r.mean(), 1e-6, 0.5))
        model = QualityModel(
            mu1=mu1,
            Sigma1=Sigma1,
            beta=beta,
            n_ref=start.n_ref,
            error_ref_px=start.error_ref_px,
            tail_weight=weight,
            tail_scale=float(np.sqrt(k2)),
        )
        nll = _mixture_nll(e, x, model)
        if previous - nll < tolerance * max(1.0, abs(nll)):
            break
        previous = nll
    return model


def _mixture_nll(e: np.ndarray, x: np.ndarray, model: QualityModel) -> float:
    """Negative log-likelihood of the samples under the (possibly tailed) model."""
    centred = e - model.mu1
    maha = np.einsum("ij,ij->i", centred @ np.linalg.inv(model.Sigma1), centred)
    return float(-model.component_log_density(maha, x @ model.beta).sum())


def _fit_log_scale(
    x: np.ndarray, maha: np.ndarray, beta: np.ndarray, free: np.ndarray
) -> np.ndarray:
    """Slopes minimising sum 0.5 m exp(-x b) + 1.5 x b (damped Newton); zeros elsewhere."""
    out = np.zeros(len(free))
    if x.shape[1] == 0:
        return out

    def cost(b: np.ndarray) -> float:
        z = x @ b
        return float(np.sum(0.5 * maha * np.exp(-z) + 1.5 * z))

    current = cost(beta)
    for _ in range(50):
        r = 0.5 * maha * np.exp(-(x @ beta))
        grad = x.T @ (1.5 - r)
        hess = (x * r[:, None]).T @ x + 1e-9 * np.eye(len(beta))
        step = np.linalg.solve(hess, -grad)
        scale = 1.0
        while scale > 1e-6:
            trial = beta + scale * step
            trial_cost = cost(trial)
            if trial_cost <= current:
                break
            scale *= 0.5
        else:
            break
        converged = current - trial_cost < 1e-12 * max(1.0, abs(current))
        beta, current = trial, trial_cost
        if converged:
            break
    out[free] = beta
    return out


def _quality_nll(centred: np.ndarray, log_scale: np.ndarray, Sigma1: np.ndarray) -> float:
    """Negative log-likelihood (up to a constant) of the samples under the model."""
    maha = np.einsum("ij,ij->i", centred @ np.linalg.inv(Sigma1), centred)
    _, log_det = np.linalg.slogdet(Sigma1)
    data_term = np.sum(0.5 * maha * np.exp(-log_scale) + 1.5 * log_scale)
    return float(data_term + 0.5 * len(maha) * log_det)


# Bounds of the PnP covariance model's fit: the effective pixel noise (px) and the floor's
# standard deviations (m, m, rad).
PNP_PIXEL_STD_BOUNDS = (0.05, 100.0)
PNP_FLOOR_STD_BOUNDS = ((1e-4, 1.0), (1e-4, 1.0), (1e-5, 0.1))


def gaussian_log_densities(residuals: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """log N(r_i; 0, S_i) of each row: residuals (N, 3), covariances (N, 3, 3) (or one
    (3, 3) for every row), by Cholesky factors."""
    L = np.linalg.cholesky(covariances)
    y = np.linalg.solve(L, residuals[:, :, None])[:, :, 0]
    return (
        -np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(axis=-1)
        - 1.5 * np.log(2.0 * np.pi)
        - 0.5 * np.einsum("ij,ij->i", y, y)
    )


def paper_log_densities(errors: np.ndarray, model: MeasurementModel) -> np.ndarray:
    """The paper pose term's log density (its mu1, Sigma1 and tail) of each pose error
    (N, 3) (x, y, heading in rad; the heading residual wrapped)."""
    r = errors - model.mu1
    r[:, 2] = wrap_angle(r[:, 2])
    maha = np.einsum("ij,ij->i", r @ np.linalg.inv(model.Sigma1), r)
    return model.paper_log_density(maha)


def fit_pnp_covariance_model(
    pose_error_samples: np.ndarray,
    pose_covariances: np.ndarray,
    outliers: MeasurementModel | None = None,
    outlier_weight: float = PAPER_TAIL_WEIGHT,
) -> PnpCovarianceModel:
    """Maximum-likelihood fit of the PnP covariance model (monoloc.core.measurement) to
    pose errors e_i (N, 3) = truth - hypothesis with their planar covariances at 1 px
    C_i (N, 3, 3): mu1, the pixel noise sigma and the diagonal floor D of
    e_i ~ (1 - w) N(mu1, sigma^2 C_i + D) + w paper(e_i), paper the pose-error density
    of ``outliers`` (the paper covariance's model fitted on the same samples: its mu1,
    Sigma1 and tail). The outlier weight w is set, as the paper covariance's tail is
    (``PAPER_TAIL_WEIGHT``: a training run shows too few of the errors it stands for to
    fit it); w = 0 or no ``outliers`` is the single Gaussian. Samples whose covariance is
    unknown (NaN) are left out. Quasi-Newton (L-BFGS-B, scipy) on mu1, log sigma and the
    log floor standard deviations within ``PNP_*_BOUNDS``."""
    from scipy.optimize import minimize

    e = np.asarray(pose_error_samples, dtype=np.float64)
    C = np.asarray(pose_covariances, dtype=np.float64)
    if e.ndim != 2 or e.shape[1] != 3 or C.shape != (len(e), 3, 3):
        raise InvalidInputError(
            f"need pose errors (N, 3) and covariances (N, 3, 3), got {e.shape} and {C.shape}"
        )
    if not 0.0 <= outlier_weight < 1.0:
        raise InvalidInputError(f"outlier_weight must be in [0, 1), got {outlier_weight}")
    known = np.isfinite(C).all(axis=(1, 2)) & np.isfinite(e).all(axis=1)
    e, C = e[known], C[known]
    if len(e) < 10:
        raise InvalidInputError(
            f"need at least 10 samples with a PnP covariance to fit the model, got {len(e)}"
        )
    if outliers is None or outlier_weight <= 0.0:
        outlier_weight, outlier_term = 0.0, None
    else:
        outlier_term = paper_log_densities(e, outliers) + np.log(outlier_weight)
    log_core = np.log1p(-outlier_weight)

    def unpack(theta):
        return theta[:3], np.exp(theta[3]), np.exp(2.0 * theta[4:7])

    def nll(theta):
        mu1, sigma, floor_var = unpack(theta)
        own = gaussian_log_densities(e - mu1, sigma**2 * C + np.diag(floor_var))
        if outlier_term is None:
            return -float(own.sum())
        return -float(np.logaddexp(own + log_core, outlier_term).sum())

    floor0 = np.log(
        [np.clip(0.5 * np.std(e[:, j]), lo, hi) for j, (lo, hi) in enumerate(PNP_FLOOR_STD_BOUNDS)]
    )
    theta0 = np.concatenate([np.median(e, axis=0), [0.0], floor0])
    bounds = [(None, None)] * 3 + [tuple(np.log(PNP_PIXEL_STD_BOUNDS))]
    bounds += [tuple(np.log(b)) for b in PNP_FLOOR_STD_BOUNDS]
    result = minimize(nll, theta0, method="L-BFGS-B", bounds=bounds)
    mu1, sigma, floor_var = unpack(result.x)
    return PnpCovarianceModel(
        mu1=mu1, pixel_std_px=float(sigma), floor=np.diag(floor_var), outlier_weight=outlier_weight
    )

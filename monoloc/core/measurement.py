"""Gaussian-mixture measurement model of METHOD.md section 7, evaluated in log space.

For a particle x = (X, Y, psi) and hypotheses i = 1..H from one frame::

    p(z | x) = sum_i c_i(x) * N(x ; z_i + mu1, Sigma1)
    c_i(x)   = N(e_i(x) ; mu2, Sigma2)
    e_i(x)   = [e_vlad_i, X_i - X, Y_i - Y, wrap(psi_i - psi)]

Everything is vectorised over particles and hypotheses (P x H). Pure numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from monoloc.core.errors import InvalidInputError


@dataclass(frozen=True)
class Hypotheses:
    """The pose hypotheses of one query frame (METHOD.md section 6 step 5).

    pose_world: (H, 3) planar (X, Y, psi) of T_world_from_query per hypothesis.
    entry_pose_world: (H, 3) planar pose of the retrieved map entry behind each.
    e_vlad: (H,) VLAD distance between the query and the entry.
    """

    pose_world: np.ndarray
    entry_pose_world: np.ndarray
    e_vlad: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.pose_world)
        shapes_ok = (
            np.shape(self.pose_world) == (n, 3)
            and np.shape(self.entry_pose_world) == (n, 3)
            and np.shape(self.e_vlad) == (n,)
        )
        if not shapes_ok:
            raise InvalidInputError(
                "hypotheses need pose_world (H,3), entry_pose_world (H,3) and e_vlad (H,), got "
                f"{np.shape(self.pose_world)}, {np.shape(self.entry_pose_world)}, "
                f"{np.shape(self.e_vlad)}"
            )

    @classmethod
    def empty(cls) -> Hypotheses:
        return cls(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))

    def __len__(self) -> int:
        return len(self.pose_world)


def _as_cov(matrix, size: int, name: str) -> np.ndarray:
    cov = np.asarray(matrix, dtype=np.float64)
    if cov.shape != (size, size) or not np.all(np.isfinite(cov)):
        raise InvalidInputError(f"{name} must be a finite {size}x{size} matrix, got {cov.shape}")
    if not np.allclose(cov, cov.T, atol=1e-9):
        raise InvalidInputError(f"{name} must be symmetric")
    try:
        np.linalg.cholesky(cov)
    except np.linalg.LinAlgError as exc:
        raise InvalidInputError(f"{name} must be positive definite") from exc
    return cov


@dataclass(frozen=True)
class MeasurementModel:
    """Parameters (mu1, Sigma1, mu2, Sigma2) of the mixture, plus monoloc's outlier floor.

    mu1 (3,), Sigma1 (3, 3): error of a hypothesis, truth minus hypothesis, in
    (m, m, rad). mu2 (4,), Sigma2 (4, 4): the retrieval vector
    [e_vlad, X_i - X, Y_i - Y, psi_i - psi] in (1, m, m, rad).
    ``outlier_log_density`` is monoloc's addition: a constant density mixed in so a frame
    whose hypotheses are all wrong cannot annihilate every particle (None disables it).
    """

    mu1: np.ndarray = field(default_factory=lambda: np.zeros(3))
    Sigma1: np.ndarray = field(
        default_factory=lambda: np.diag([0.25**2, 0.25**2, math.radians(1.5) ** 2])
    )
    mu2: np.ndarray = field(default_factory=lambda: np.array([0.9, 0.0, 0.0, 0.0]))
    Sigma2: np.ndarray = field(
        default_factory=lambda: np.diag([0.25**2, 8.0**2, 8.0**2, math.radians(30.0) ** 2])
    )
    outlier_log_density: float | None = -16.0
    source: str = "defaults"

    def __post_init__(self) -> None:
        object.__setattr__(self, "mu1", np.asarray(self.mu1, dtype=np.float64).reshape(3))
        object.__setattr__(self, "mu2", np.asarray(self.mu2, dtype=np.float64).reshape(4))
        object.__setattr__(self, "Sigma1", _as_cov(self.Sigma1, 3, "Sigma1"))
        object.__setattr__(self, "Sigma2", _as_cov(self.Sigma2, 4, "Sigma2"))
        # Whitening matrices and normalisers, computed once: the per-step cost is then
        # one small matmul per component family.
        object.__setattr__(self, "_whiten1", _whitening(self.Sigma1))
        object.__setattr__(self, "_whiten2", _whitening(self.Sigma2))
        object.__setattr__(self, "_log_norm1", _log_normaliser(self.Sigma1))
        object.__setattr__(self, "_log_norm2", _log_normaliser(self.Sigma2))

    def to_dict(self) -> dict:
        return {
            "mu1": self.mu1.tolist(),
            "Sigma1": self.Sigma1.tolist(),
            "mu2": self.mu2.tolist(),
            "Sigma2": self.Sigma2.tolist(),
            "outlier_log_density": self.outlier_log_density,
            "source": self.source,
        }

    @classmethod
    def from_dict(cls, data: dict) -> MeasurementModel:
        try:
            return cls(
                mu1=data["mu1"],
                Sigma1=data["Sigma1"],
                mu2=data["mu2"],
                Sigma2=data["Sigma2"],
                outlier_log_density=data.get("outlier_log_density", -16.0),
                source=str(data.get("source", "calibrated")),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise InvalidInputError(f"malformed measurement model parameters: {exc}") from exc


def _whitening(cov: np.ndarray) -> np.ndarray:
    """W with W^T W = cov^-1, so |W r|^2 is the Mahalanobis distance."""
    return np.linalg.inv(np.linalg.cholesky(cov))


def _log_normaliser(cov: np.ndarray) -> float:
    sign, log_det = np.linalg.slogdet(cov)
    return -0.5 * (log_det + cov.shape[0] * math.log(2.0 * math.pi))


def _wrap_residual(angle_rad: np.ndarray) -> np.ndarray:
    """Cheap wrap to [-pi, pi] for residuals (the +-pi tie does not matter when squared)."""
    return angle_rad - (2.0 * math.pi) * np.round(angle_rad / (2.0 * math.pi))


def gaussian_log_pdf(residuals: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """log N(r; 0, cov) for residuals (..., D). Returns (...)."""
    dim = cov.shape[0]
    chol = np.linalg.cholesky(cov)
    flat = residuals.reshape(-1, dim)
    # Solve L y = r^T for all residuals at once; Mahalanobis = |y|^2.
    y = np.linalg.solve(chol, flat.T)
    maha = np.einsum("ij,ij->j", y, y).reshape(residuals.shape[:-1])
    log_det = 2.0 * np.sum(np.log(np.diag(chol)))
    return -0.5 * (maha + log_det + dim * math.log(2.0 * math.pi))


def log_likelihood(
    particles: np.ndarray, hypotheses: Hypotheses, model: MeasurementModel
) -> np.ndarray:
    """log p(z | x) for each particle. particles (P, 3) -> (P,). Needs >= 1 hypothesis."""
    return log_likelihood_and_distance(particles, hypotheses, model)[0]


def log_likelihood_and_distance(
    particles: np.ndarray, hypotheses: Hypotheses, model: MeasurementModel
) -> tuple[np.ndarray, float]:
    """log p(z | x) per particle (P,), and the smallest squared Mahalanobis distance
    (under Sigma1) between any particle and any bias-corrected hypothesis: how far the
    whole particle set is from what this frame says (the filter's "lost" signal)."""
    if len(hypotheses) == 0:
        raise InvalidInputError("log_likelihood needs at least one hypothesis")
    # Work column by column on (P, H) arrays: with 3- and 4-vectors this beats batched
    # matmuls by a wide margin (see bench/filter.py).
    X, Y, psi = (particles[:, k : k + 1] for k in range(3))
    # Component: N(x; z_i + mu1, Sigma1), residual x - (z_i + mu1) with wrapped heading.
    centres = hypotheses.pose_world + model.mu1  # (H, 3)
    r1 = [X - centres[:, 0], Y - centres[:, 1], _wrap_residual(psi - centres[:, 2])]
    maha1 = _mahalanobis(r1, model._whiten1)
    closest = float(maha1.min())
    terms = model._log_norm1 - 0.5 * maha1
    # Weight: N(e_i(x); mu2, Sigma2), e_i(x) = [e_vlad, X_i - X, Y_i - Y, psi_i - psi].
    entries = hypotheses.entry_pose_world - model.mu2[1:]  # (H, 3)
    r2 = [
        np.broadcast_to(hypotheses.e_vlad - model.mu2[0], terms.shape),
        entries[:, 0] - X,
        entries[:, 1] - Y,
        _wrap_residual(entries[:, 2] - psi),
    ]
    terms += model._log_norm2 - 0.5 * _mahalanobis(r2, model._whiten2)
    peak = terms.max(axis=1)
    if model.outlier_log_density is not None:
        peak = np.maximum(peak, model.outlier_log_density)
    total = np.exp(terms - peak[:, None]).sum(axis=1)
    if model.outlier_log_density is not None:
        total += np.exp(model.outlier_log_density - peak)
    return peak + np.log(total), closest


def _mahalanobis(residuals: list[np.ndarray], whiten: np.ndarray) -> np.ndarray:
    """|W r|^2 for residual components r_k (each (P, H)) and lower-triangular W (D, D)."""
    total = None
    for row in range(len(residuals)):
        w = residuals[0] * whiten[row, 0]
        for col in range(1, row + 1):
            w = w + residuals[col] * whiten[row, col]
        total = w * w if total is None else total + w * w
    return total

"""Gaussian-mixture measurement model of docs/method.md section 7, evaluated in log space.

For a particle x = (X, Y, psi) and hypotheses i = 1..H from one frame::

    p(z | x) = sum_i c_i(x) * N(x ; z_i + mu1, Sigma1)
    c_i(x)   = N(e_i(x) ; mu2, Sigma2)
    e_i(x)   = [e_vlad_i, X_i - X, Y_i - Y, wrap(psi_i - psi)]

Everything is vectorised over particles and hypotheses (P x H). Pure numpy.

The product's choices are :data:`DEFAULT_COVARIANCE` (each hypothesis's own PnP
covariance) and :data:`DEFAULT_RETRIEVAL_FRAME` (offsets along and across the vehicle's
heading). The variants beside them ("paper" and "quality" covariances, the paper's world
axes) stay reachable here for bench/ and for calibrations stored with them; the API does
not offer them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from monoloc.core.errors import InvalidInputError


@dataclass(frozen=True)
class Hypotheses:
    """The pose hypotheses of one query frame (docs/method.md section 6 step 5).

    pose_world: (H, 3) planar (X, Y, psi) of T_world_from_query per hypothesis.
    entry_pose_world: (H, 3) planar pose of the retrieved map entry behind each.
    e_vlad: (H,) VLAD distance between the query and the entry.
    Quality features, optional (None: unknown, e.g. an old server): n_inliers (H,) PnP
    inliers, reprojection_error_px (H,) their mean error, joint (H,) bool: the hypothesis
    is the joint pose of several entries, not one entry's; pose_covariance (H, 3, 3): the
    planar pose's (X m, Y m, psi rad) covariance from the hypothesis's own inliers at 1 px
    of pixel noise (the server's ``vision.pose_covariance``; a joint or pooled pose's from
    the inliers of all its entries), NaN for a hypothesis without one (an older server's
    joint or pooled pose). entry_tags (H,) tuples of str, optional: the tags of the entry
    behind each hypothesis (a joint pose's: its anchor's), e.g. ("night",); they select a
    condition's calibration (``MeasurementModel.conditions``). method (H,) str, optional:
    how the server found each pose ("ransac", "guided", "joint", "pooled",
    "alternative"; ``PoseHypothesis.method``).
    """

    pose_world: np.ndarray
    entry_pose_world: np.ndarray
    e_vlad: np.ndarray
    n_inliers: np.ndarray | None = None
    reprojection_error_px: np.ndarray | None = None
    joint: np.ndarray | None = None
    pose_covariance: np.ndarray | None = None
    entry_tags: tuple[tuple[str, ...], ...] | None = None
    method: tuple[str, ...] | None = None

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
        for name in ("n_inliers", "reprojection_error_px", "joint"):
            value = getattr(self, name)
            if value is not None and np.shape(value) != (n,):
                raise InvalidInputError(f"hypotheses' {name} must be ({n},), got {np.shape(value)}")
        if self.joint is not None:
            object.__setattr__(self, "joint", np.asarray(self.joint, dtype=bool))
        if self.pose_covariance is not None:
            cov = np.asarray(self.pose_covariance, dtype=np.float64)
            if cov.shape != (n, 3, 3):
                raise InvalidInputError(
                    f"hypotheses' pose_covariance must be ({n}, 3, 3), got {cov.shape}"
                )
            object.__setattr__(self, "pose_covariance", cov)
        if self.entry_tags is not None:
            tags = tuple(tuple(str(t) for t in entry) for entry in self.entry_tags)
            if len(tags) != n:
                raise InvalidInputError(
                    f"hypotheses' entry_tags must hold {n} tuples, got {len(tags)}"
                )
            object.__setattr__(self, "entry_tags", tags)
        if self.method is not None:
            method = tuple(str(m) for m in self.method)
            if len(method) != n:
                raise InvalidInputError(
                    f"hypotheses' method must hold {n} names, got {len(method)}"
                )
            object.__setattr__(self, "method", method)

    @property
    def has_quality(self) -> bool:
        """Whether the quality features are known (n_inliers and reprojection errors)."""
        return self.n_inliers is not None and self.reprojection_error_px is not None

    def without_joint(self) -> Hypotheses:
        """The per-entry hypotheses only (the paper's model has no joint pose)."""
        if self.joint is None or not self.joint.any():
            return self
        return self.subset(~self.joint)

    def subset(self, keep: np.ndarray) -> Hypotheses:
        """The hypotheses selected by ``keep`` (a boolean mask or indices), every field
        kept."""
        keep = np.asarray(keep)
        index = np.flatnonzero(keep) if keep.dtype == bool else keep.astype(np.intp)

        def pick(values):
            return None if values is None else values[index]

        return Hypotheses(
            self.pose_world[index],
            self.entry_pose_world[index],
            self.e_vlad[index],
            pick(self.n_inliers),
            pick(self.reprojection_error_px),
            pick(self.joint),
            pick(self.pose_covariance),
            None if self.entry_tags is None else tuple(self.entry_tags[i] for i in index),
            None if self.method is None else tuple(self.method[i] for i in index),
        )

    @classmethod
    def empty(cls) -> Hypotheses:
        return cls(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))

    def __len__(self) -> int:
        return len(self.pose_world)


def _turn(heading_rad: np.ndarray) -> np.ndarray:
    """R (H, 3, 3): planar rotations by each heading, the angle axis left alone."""
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    R = np.zeros((len(c), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def to_world_axes(cov: np.ndarray, heading_rad: np.ndarray) -> np.ndarray:
    """Covariances (H, 3, 3) in world axes of (along, across, psi) covariances (3, 3) or
    (H, 3, 3) along and across each heading (H,)."""
    R = _turn(np.asarray(heading_rad, dtype=np.float64).reshape(-1))
    return R @ cov @ R.transpose(0, 2, 1)


def to_heading_axes(
    errors: np.ndarray, heading_rad: np.ndarray, cov: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Pose errors (N, 3) (X, Y, psi) and covariances (N, 3, 3), optional, in world axes
    turned along and across each heading (N,): what a vehicle-frame pose term is fitted
    on (the inverse of :func:`to_world_axes`)."""
    R = _turn(np.asarray(heading_rad, dtype=np.float64).reshape(-1))
    Rt = R.transpose(0, 2, 1)
    along = np.einsum("nij,nj->ni", Rt, np.asarray(errors, dtype=np.float64))
    return along, None if cov is None else Rt @ np.asarray(cov, dtype=np.float64) @ R


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


QUALITY_FEATURES = ("log_inliers", "log_reprojection_error", "joint")


def quality_features(
    n_inliers: np.ndarray,
    reprojection_error_px: np.ndarray,
    joint: np.ndarray | None,
    n_ref: float,
    error_ref_px: float,
) -> np.ndarray:
    """Features (H, 3) of the quality model: log(n / n_ref), log(err / err_ref), joint."""
    n = np.maximum(np.asarray(n_inliers, dtype=np.float64), 1.0)
    err = np.maximum(np.asarray(reprojection_error_px, dtype=np.float64), 1e-3)
    out = np.empty((len(n), 3))
    out[:, 0] = np.log(n / n_ref)
    out[:, 1] = np.log(err / error_ref_px)
    out[:, 2] = 0.0 if joint is None else np.asarray(joint, dtype=np.float64)
    return out


@dataclass(frozen=True)
class QualityModel:
    """Quality-aware pose-error model: hypothesis i has error (truth - z_i) ~
    N(mu1, s_i Sigma1) with log s_i = beta . quality_features(i), clipped to
    ``log_scale_bounds``.

    mu1 (3,), Sigma1 (3, 3): bias and covariance (m, m, rad) of a per-entry hypothesis
    with ``n_ref`` inliers at ``error_ref_px`` mean reprojection error. beta (3,): slopes
    for log(n_inliers / n_ref), log(error / error_ref_px) and the joint flag.

    Heavy tail: with ``tail_weight`` eps > 0 the error is the scale mixture
    (1 - eps) N(mu1, s_i Sigma1) + eps N(mu1, tail_scale^2 s_i Sigma1). PnP errors are far
    from Gaussian (kurtosis 20-30 even after the quality scaling, on the sim's training
    runs): one Gaussian fitted to them is wide where most hypotheses are precise and
    narrow where the rare bad one lands, which then pulls the particles hard. 0 (a model
    stored before the tail existed) is the single Gaussian.
    """

    mu1: np.ndarray = field(default_factory=lambda: np.zeros(3))
    Sigma1: np.ndarray = field(
        default_factory=lambda: np.diag([0.1**2, 0.1**2, math.radians(0.5) ** 2])
    )
    beta: np.ndarray = field(default_factory=lambda: np.array([-1.0, 1.0, 0.0]))
    n_ref: float = 100.0
    error_ref_px: float = 1.0
    log_scale_bounds: tuple[float, float] = (-6.0, 6.0)
    tail_weight: float = 0.0
    tail_scale: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "mu1", np.asarray(self.mu1, dtype=np.float64).reshape(3))
        object.__setattr__(self, "beta", np.asarray(self.beta, dtype=np.float64).reshape(3))
        object.__setattr__(self, "Sigma1", _as_cov(self.Sigma1, 3, "quality Sigma1"))
        object.__setattr__(self, "tail_weight", float(self.tail_weight))
        object.__setattr__(self, "tail_scale", float(self.tail_scale))
        lo, hi = (float(b) for b in self.log_scale_bounds)
        if not (
            np.all(np.isfinite(self.mu1))
            and np.all(np.isfinite(self.beta))
            and self.n_ref > 0
            and self.error_ref_px > 0
            and lo < hi
            and 0.0 <= self.tail_weight < 1.0
            and 1.0 <= self.tail_scale < 1e3
        ):
            raise InvalidInputError(f"invalid quality model {self}")
        object.__setattr__(self, "log_scale_bounds", (lo, hi))
        object.__setattr__(self, "_whiten", _whitening(self.Sigma1))
        object.__setattr__(self, "_log_norm", _log_normaliser(self.Sigma1))

    def log_scale(self, hypotheses: Hypotheses) -> np.ndarray:
        """log s_i (H,) of each hypothesis (needs its quality features)."""
        x = quality_features(
            hypotheses.n_inliers,
            hypotheses.reprojection_error_px,
            hypotheses.joint,
            self.n_ref,
            self.error_ref_px,
        )
        return np.clip(x @ self.beta, *self.log_scale_bounds)

    def to_dict(self) -> dict:
        return {
            "mu1": self.mu1.tolist(),
            "Sigma1": self.Sigma1.tolist(),
            "beta": self.beta.tolist(),
            "features": list(QUALITY_FEATURES),
            "n_ref": self.n_ref,
            "error_ref_px": self.error_ref_px,
            "log_scale_bounds": list(self.log_scale_bounds),
            "tail_weight": self.tail_weight,
            "tail_scale": self.tail_scale,
        }

    def spread(self) -> float:
        """Variance of the error over that of its core, (1 - eps) + eps tail_scale^2: the
        mixture's covariance is spread() s_i Sigma1."""
        return (1.0 - self.tail_weight) + self.tail_weight * self.tail_scale**2

    def component_log_density(self, maha: np.ndarray, log_scale: np.ndarray) -> np.ndarray:
        """log of the pose-error density for Mahalanobis distances ``maha`` (..., H) under
        Sigma1 (unscaled) and log scales (H,): the core Gaussian, or the core and the tail
        mixed."""
        norm = self._log_norm - 1.5 * log_scale
        return _scale_mixture_log_density(
            norm, maha * np.exp(-log_scale), self.tail_weight, self.tail_scale
        )

    @classmethod
    def from_dict(cls, data: dict) -> QualityModel:
        defaults = cls()
        return cls(
            mu1=data["mu1"],
            Sigma1=data["Sigma1"],
            beta=data["beta"],
            n_ref=float(data.get("n_ref", defaults.n_ref)),
            error_ref_px=float(data.get("error_ref_px", defaults.error_ref_px)),
            log_scale_bounds=tuple(data.get("log_scale_bounds", defaults.log_scale_bounds)),
            tail_weight=float(data.get("tail_weight", 0.0)),
            tail_scale=float(data.get("tail_scale", 1.0)),
        )


@dataclass(frozen=True)
class PnpCovarianceModel:
    """Pose-error model from each hypothesis's own PnP geometry: hypothesis i has error
    (truth - z_i) ~ N(mu1, S_i), S_i = pixel_std_px^2 C_i + floor, C_i its planar pose
    covariance at 1 px (``Hypotheses.pose_covariance``: where its inliers lie, how many,
    how deep, from which pyramid level), ``pixel_std_px`` the effective pixel noise of a
    full-resolution keypoint and ``floor`` (3, 3) what the geometry does not see (the map
    points' own errors).

    Outliers: with probability ``outlier_weight`` a hypothesis's error does not follow its
    geometry at all (a moved car that carries most inliers, a lone pose at the map's end,
    an aliased facade: precise-looking and wrong) and is drawn from the paper covariance's
    model instead (the MeasurementModel's mu1, Sigma1 and tail, fitted on every
    hypothesis). A tail scaled from S_i would not do: a precise-looking wrong pose would
    then pull the particles as hard as a right one. A pooled pose's C_i comes from the
    inliers of all its entries; a hypothesis without C_i (an older server's pooled pose)
    follows the paper's model alone; joint poses are left out, as in the paper's model
    (keeping them gained nothing measurable). Fitted by maximum likelihood
    (``core.calibration.fit_pnp_covariance_model``).
    """

    mu1: np.ndarray = field(default_factory=lambda: np.zeros(3))
    pixel_std_px: float = 1.0
    floor: np.ndarray = field(
        default_factory=lambda: np.diag([0.02**2, 0.02**2, math.radians(0.1) ** 2])
    )
    outlier_weight: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "mu1", np.asarray(self.mu1, dtype=np.float64).reshape(3))
        object.__setattr__(self, "floor", _as_cov(self.floor, 3, "PnP covariance floor"))
        object.__setattr__(self, "pixel_std_px", float(self.pixel_std_px))
        object.__setattr__(self, "outlier_weight", float(self.outlier_weight))
        if not (
            np.all(np.isfinite(self.mu1))
            and 0.0 < self.pixel_std_px < 1e3
            and 0.0 <= self.outlier_weight < 1.0
        ):
            raise InvalidInputError(f"invalid PnP covariance model {self}")

    def covariances(
        self, pose_covariance: np.ndarray, heading_rad: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """S_i (H, 3, 3) of hypotheses with planar covariances (H, 3, 3) at 1 px, and
        which of them have one (H,) bool (where not, S_i is the identity: unused).
        ``heading_rad`` (H,): the floor is along / across each hypothesis's heading
        (a model in the vehicle frame), turned into world axes here."""
        C = np.asarray(pose_covariance, dtype=np.float64)
        known = np.isfinite(C).all(axis=(1, 2))
        out = np.broadcast_to(np.eye(3), C.shape).copy()
        floor = self.floor if heading_rad is None else to_world_axes(self.floor, heading_rad)
        floor = np.broadcast_to(floor, C.shape)
        out[known] = self.pixel_std_px**2 * C[known] + floor[known]
        return out, known

    def to_dict(self) -> dict:
        return {
            "mu1": self.mu1.tolist(),
            "pixel_std_px": self.pixel_std_px,
            "floor": self.floor.tolist(),
            "outlier_weight": self.outlier_weight,
        }

    @classmethod
    def from_dict(cls, data: dict) -> PnpCovarianceModel:
        return cls(
            mu1=data["mu1"],
            pixel_std_px=float(data["pixel_std_px"]),
            floor=data["floor"],
            outlier_weight=float(data.get("outlier_weight", 0.0)),
        )


CovarianceModel = Literal["paper", "quality", "pnp"]
RetrievalFrame = Literal["world", "vehicle"]

DEFAULT_COVARIANCE: CovarianceModel = "pnp"
"""The pose-error model the product calibrates and selects. A model without its
parameters (the documented defaults, a calibration stored before it) uses the paper's."""
DEFAULT_RETRIEVAL_FRAME: RetrievalFrame = "vehicle"
"""The axes of the model's offsets: along and across the vehicle's heading (the particle's
for the retrieval vector, the hypothesis's for the pose error), which a calibration keeps
on a street running another way; the paper's world axes remembered the training road's
direction (docs/notebook/transfer.md, 2026-12-02, third entry)."""
VladEvidence = Literal["absolute", "relative"]
DEFAULT_VLAD_EVIDENCE: VladEvidence = "absolute"
"""How the retrieval term reads a hypothesis's VLAD distance: "absolute" (the paper's
e_vlad_i) or "relative" (e_vlad_i minus the smallest of its frame's hypotheses, which
does not move with a street's overall VLAD distances; ``MeasurementModel.vlad_evidence``)."""
DEFAULT_RELATIVE_VLAD = (0.0, 0.25)
"""(mean, std) of the relative VLAD distance for a model without a calibrated one: as
loose as the default absolute term's spread."""


@dataclass(frozen=True)
class MeasurementModel:
    """Parameters (mu1, Sigma1, mu2, Sigma2) of the mixture, plus monoloc's outlier floor.

    mu1 (3,), Sigma1 (3, 3): error of a hypothesis, truth minus hypothesis, in
    (m, m, rad), in ``retrieval_frame``'s axes. mu2 (4,), Sigma2 (4, 4): the retrieval
    vector [e_vlad, X_i - X, Y_i - Y, psi_i - psi] in (1, m, m, rad), the offset in
    ``retrieval_frame``'s axes.
    ``outlier_log_density`` is monoloc's addition: a constant density mixed in so a frame
    whose hypotheses are all wrong cannot annihilate every particle (None disables it).
    ``tail_weight`` eps and ``tail_scale`` k, also monoloc's (paper covariance only; the
    quality model has its own fitted tail): each hypothesis's pose error is
    (1 - eps) N(mu1, Sigma1) + eps N(mu1, k^2 Sigma1), so a hypothesis a few decimetres
    off pulls the particles near the truth by 1/k^2 of a Gaussian's pull instead of
    dragging the cloud onto itself. eps = 0 (the default, and a calibration stored before
    the tail existed) is the paper's single Gaussian.
    ``covariance`` selects the pose-error model: "paper" (mu1, Sigma1 for all, joint
    hypotheses left out), "quality" (``quality``'s per-hypothesis covariance; needs
    ``quality``) or "pnp" (``pnp``'s covariance from each hypothesis's own PnP geometry,
    joint hypotheses left out; needs ``pnp``); None picks :data:`DEFAULT_COVARIANCE`
    when its parameters are given, else "paper". ``with_covariance`` switches between
    them. ``retrieval_frame``: the axes of the model's planar offsets. "vehicle" (the
    product's, :data:`DEFAULT_RETRIEVAL_FRAME`): the retrieval vector's offset along and
    across the particle's heading, and the pose error's bias and covariance (mu1, Sigma1,
    the quality model's, the PnP floor and bias; not a hypothesis's own PnP covariance,
    which is in world axes) along and across the hypothesis's heading, so that nothing
    depends on how the map's world frame is turned. "world": all of them in world axes,
    as in the paper; a calibration stored before the choice existed or stored with it is
    applied so.
    ``vlad_evidence``: "absolute" (the paper's e_vlad term, mu2[0] and Sigma2's first
    row) or "relative": the retrieval weight is N(e_vlad_i - min_j e_vlad_j;
    ``relative_vlad`` (mean, std)) times the offsets' Gaussian (mu2[1:], Sigma2[1:, 1:]),
    the VLAD distance read against the frame's own best (a street whose every VLAD
    distance is larger than the training street's no longer pushes every hypothesis
    under the outlier floor).
    ``conditions``: models calibrated on a training run of one condition, by the entry tag
    that names it (e.g. "night": a night training run against its own night map). A
    hypothesis whose entry carries that tag (``Hypotheses.entry_tags``) is weighed by that
    model's mixture terms (pose error and retrieval vector) instead of this one's; the
    outlier floor stays this model's. A night query matched to night entries has errors
    of its own (fewer, noisier features on the lit road, more aliasing); a day-calibrated
    model is too sure of them. Empty: one model for every hypothesis.
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
    quality: QualityModel | None = None
    covariance: CovarianceModel | None = None
    pnp: PnpCovarianceModel | None = None
    retrieval_frame: RetrievalFrame = DEFAULT_RETRIEVAL_FRAME
    vlad_evidence: VladEvidence = DEFAULT_VLAD_EVIDENCE
    relative_vlad: tuple[float, float] = DEFAULT_RELATIVE_VLAD
    tail_weight: float = 0.0
    tail_scale: float = 1.0
    conditions: dict[str, MeasurementModel] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "tail_weight", float(self.tail_weight))
        object.__setattr__(self, "tail_scale", float(self.tail_scale))
        conditions = dict(self.conditions or {})
        for name, model in conditions.items():
            if not isinstance(name, str) or not name.strip():
                raise InvalidInputError(f"a condition needs a non-empty tag name, got {name!r}")
            if not isinstance(model, MeasurementModel) or model.conditions:
                raise InvalidInputError(
                    f"condition {name!r} must be a measurement model without conditions"
                )
        object.__setattr__(self, "conditions", dict(sorted(conditions.items())))
        if not (0.0 <= self.tail_weight < 1.0 and 1.0 <= self.tail_scale < 1e3):
            raise InvalidInputError(
                "tail_weight must be in [0, 1) and tail_scale in [1, 1000), got "
                f"{self.tail_weight} and {self.tail_scale}"
            )
        if self.covariance is None:
            parameters = {"paper": self.Sigma1, "quality": self.quality, "pnp": self.pnp}
            chosen = DEFAULT_COVARIANCE if parameters[DEFAULT_COVARIANCE] is not None else "paper"
            object.__setattr__(self, "covariance", chosen)
        if self.covariance not in ("paper", "quality", "pnp"):
            raise InvalidInputError(
                f"covariance must be 'paper', 'quality' or 'pnp', got {self.covariance!r}"
            )
        if self.retrieval_frame not in ("world", "vehicle"):
            raise InvalidInputError(
                f"retrieval_frame must be 'world' or 'vehicle', got {self.retrieval_frame!r}"
            )
        if self.vlad_evidence not in ("absolute", "relative"):
            raise InvalidInputError(
                f"vlad_evidence must be 'absolute' or 'relative', got {self.vlad_evidence!r}"
            )
        mean_rel, std_rel = (float(v) for v in self.relative_vlad)
        if not (math.isfinite(mean_rel) and math.isfinite(std_rel) and std_rel > 0):
            raise InvalidInputError(
                f"relative_vlad must be a finite (mean, std > 0), got {self.relative_vlad!r}"
            )
        object.__setattr__(self, "relative_vlad", (mean_rel, std_rel))
        if self.covariance == "quality" and self.quality is None:
            raise InvalidInputError("the quality covariance model needs quality parameters")
        if self.covariance == "pnp" and self.pnp is None:
            raise InvalidInputError("the pnp covariance model needs its fitted parameters")
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
        offsets = self.Sigma2[1:, 1:]
        object.__setattr__(self, "_whiten2_offsets", _whitening(offsets))
        object.__setattr__(
            self,
            "_log_norm2_relative",
            _log_normaliser(offsets) - math.log(std_rel) - 0.5 * math.log(2.0 * math.pi),
        )

    def to_dict(self) -> dict:
        return {
            "mu1": self.mu1.tolist(),
            "Sigma1": self.Sigma1.tolist(),
            "mu2": self.mu2.tolist(),
            "Sigma2": self.Sigma2.tolist(),
            "outlier_log_density": self.outlier_log_density,
            "source": self.source,
            "quality": None if self.quality is None else self.quality.to_dict(),
            "covariance": self.covariance,
            "pnp": None if self.pnp is None else self.pnp.to_dict(),
            "retrieval_frame": self.retrieval_frame,
            "vlad_evidence": self.vlad_evidence,
            "relative_vlad": list(self.relative_vlad),
            "tail_weight": self.tail_weight,
            "tail_scale": self.tail_scale,
            "conditions": {name: model.to_dict() for name, model in self.conditions.items()},
        }

    def paper_log_density(self, maha: np.ndarray) -> np.ndarray:
        """log of the paper covariance's pose-error density for squared Mahalanobis
        distances ``maha`` under Sigma1: the Gaussian, or with the tail mixed in."""
        return _scale_mixture_log_density(self._log_norm1, maha, self.tail_weight, self.tail_scale)

    def hypothesis_gaussians(self, hypotheses: Hypotheses) -> tuple[np.ndarray, np.ndarray]:
        """Each hypothesis's pose as this model sees it: the bias-corrected pose (H, 3)
        z_i + mu1 and the covariance (H, 3, 3) of its error's core Gaussian (tails
        aside): "pnp": pixel_std^2 C_i + floor where the hypothesis has its C_i (joint
        poses included), "quality": s_i Sigma1 where the quality features are known, the
        paper's Sigma1 otherwise; each under its condition's model (``conditions``)."""
        groups = self.by_condition(hypotheses)
        if len(groups) == 1:
            return groups[0][0]._own_gaussians(hypotheses)
        centres = np.empty((len(hypotheses), 3))
        covs = np.empty((len(hypotheses), 3, 3))
        for model, index in groups:
            centres[index], covs[index] = model._own_gaussians(hypotheses.subset(index))
        return centres, covs

    def _own_gaussians(self, hypotheses: Hypotheses) -> tuple[np.ndarray, np.ndarray]:
        n = len(hypotheses)
        heading = self._pose_headings(hypotheses)
        centres = self.corrected(hypotheses, self.mu1)
        covs = np.broadcast_to(self._in_world(self.Sigma1, heading), (n, 3, 3)).copy()
        if self.covariance == "pnp" and hypotheses.pose_covariance is not None:
            S, known = self.pnp.covariances(hypotheses.pose_covariance, heading)
            covs[known] = S[known]
            centres[known] = self.corrected(hypotheses, self.pnp.mu1)[known]
        elif self.covariance == "quality" and hypotheses.has_quality:
            scale = np.exp(self.quality.log_scale(hypotheses))
            covs = scale[:, None, None] * self._in_world(self.quality.Sigma1, heading)
            centres = self.corrected(hypotheses, self.quality.mu1)
        return centres, covs

    def _pose_headings(self, hypotheses: Hypotheses) -> np.ndarray | None:
        """The headings (H,) the pose error's parameters are along / across (the
        hypotheses' own, vehicle frame), None in world axes."""
        return None if self.retrieval_frame == "world" else hypotheses.pose_world[:, 2]

    @staticmethod
    def _in_world(cov: np.ndarray, heading: np.ndarray | None) -> np.ndarray:
        return cov if heading is None else to_world_axes(cov, heading)

    def corrected(self, hypotheses: Hypotheses, mu1: np.ndarray | None = None) -> np.ndarray:
        """The bias-corrected poses (H, 3) z_i + mu1 (``mu1``: this model's by default),
        the bias along / across each hypothesis's heading in the vehicle frame."""
        mu1 = self.mu1 if mu1 is None else mu1
        poses = hypotheses.pose_world
        if self.retrieval_frame == "world":
            return poses + mu1
        c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        return poses + np.column_stack(
            [c * mu1[0] - s * mu1[1], s * mu1[0] + c * mu1[1]] + [np.full(len(poses), mu1[2])]
        )

    def by_condition(self, hypotheses: Hypotheses) -> list[tuple[MeasurementModel, np.ndarray]]:
        """The hypotheses grouped by the model that weighs them: (model, indices) pairs,
        this model's group first when it has one. A hypothesis goes to the first condition
        (by name) among its entry's tags, to this model when none has a calibration."""
        n = len(hypotheses)
        if not self.conditions or hypotheses.entry_tags is None:
            return [(self, np.arange(n))]
        names = list(self.conditions)
        which = np.array(
            [
                next((k + 1 for k, c in enumerate(names) if c in tags), 0)
                for tags in hypotheses.entry_tags
            ],
            dtype=np.intp,
        )
        models = [self, *self.conditions.values()]
        return [
            (models[k], np.flatnonzero(which == k))
            for k in range(len(models))
            if (which == k).any()
        ]

    def with_condition(self, name: str, model: MeasurementModel) -> MeasurementModel:
        """This model with ``model`` (its own conditions dropped) as condition ``name``'s."""
        own = dataclasses.replace(model, conditions={})
        return dataclasses.replace(self, conditions={**self.conditions, name: own})

    def with_covariance(self, covariance: CovarianceModel) -> MeasurementModel:
        """The same parameters with the other covariance model selected (in every
        condition's model too)."""
        return dataclasses.replace(
            self,
            covariance=covariance,
            conditions={
                name: dataclasses.replace(model, covariance=covariance)
                for name, model in self.conditions.items()
            },
        )

    def with_vlad_evidence(self, vlad_evidence: VladEvidence) -> MeasurementModel:
        """The same parameters reading the VLAD distance the other way (in every
        condition's model too)."""
        return dataclasses.replace(
            self,
            vlad_evidence=vlad_evidence,
            conditions={
                name: dataclasses.replace(model, vlad_evidence=vlad_evidence)
                for name, model in self.conditions.items()
            },
        )

    @classmethod
    def from_dict(cls, data: dict) -> MeasurementModel:
        """Parameters from :meth:`to_dict` output; a calibration stored before the quality
        model existed (no ``quality`` / ``covariance``) loads as the paper's model, one
        stored before the PnP covariance model without it (``pnp`` None), one stored
        before the retrieval frame was a choice in the world frame, one stored before the
        VLAD evidence was a choice with the absolute term."""
        try:
            quality = data.get("quality")
            return cls(
                mu1=data["mu1"],
                Sigma1=data["Sigma1"],
                mu2=data["mu2"],
                Sigma2=data["Sigma2"],
                outlier_log_density=data.get("outlier_log_density", -16.0),
                source=str(data.get("source", "calibrated")),
                quality=None if quality is None else QualityModel.from_dict(quality),
                covariance=data.get("covariance"),
                pnp=None if data.get("pnp") is None else PnpCovarianceModel.from_dict(data["pnp"]),
                retrieval_frame=data.get("retrieval_frame") or "world",
                vlad_evidence=data.get("vlad_evidence") or "absolute",
                relative_vlad=tuple(data.get("relative_vlad") or DEFAULT_RELATIVE_VLAD),
                tail_weight=float(data.get("tail_weight") or 0.0),
                tail_scale=float(data.get("tail_scale") or 1.0),
                conditions={
                    str(name): cls.from_dict(values)
                    for name, values in (data.get("conditions") or {}).items()
                },
            )
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise InvalidInputError(f"malformed measurement model parameters: {exc}") from exc


def _scale_mixture_log_density(
    log_norm: float | np.ndarray, maha: np.ndarray, tail_weight: float, tail_scale: float
) -> np.ndarray:
    """log[(1 - eps) N + eps N(k^2 cov)] of 3-vectors at squared Mahalanobis distances
    ``maha`` under cov, whose Gaussian has log normaliser ``log_norm``; eps = 0: the
    Gaussian alone."""
    core = log_norm - 0.5 * maha
    if tail_weight <= 0.0:
        return core
    k2 = tail_scale**2
    tail = (log_norm - 1.5 * math.log(k2)) - 0.5 * maha / k2
    return np.logaddexp(core + math.log1p(-tail_weight), tail + math.log(tail_weight))


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
    (under its covariance) between any particle and any bias-corrected hypothesis: how far the
    whole particle set is from what this frame says (the filter's "lost" signal). Each
    hypothesis's terms come from its condition's model (``MeasurementModel.by_condition``)."""
    if len(hypotheses) == 0:
        raise InvalidInputError("log_likelihood needs at least one hypothesis")
    groups = model.by_condition(hypotheses)
    # the frame's best VLAD distance, over all its hypotheses (the relative evidence)
    vlad_best = float(np.min(hypotheses.e_vlad))
    if len(groups) == 1:
        terms, closest = _mixture_terms(particles, hypotheses, groups[0][0], vlad_best)
    else:
        parts = [_mixture_terms(particles, hypotheses.subset(i), m, vlad_best) for m, i in groups]
        terms = np.concatenate([t for t, _ in parts], axis=1)
        closest = min(c for _, c in parts)
    peak = terms.max(axis=1)
    if model.outlier_log_density is not None:
        peak = np.maximum(peak, model.outlier_log_density)
    total = np.exp(terms - peak[:, None]).sum(axis=1)
    if model.outlier_log_density is not None:
        total += np.exp(model.outlier_log_density - peak)
    return peak + np.log(total), closest


def _mixture_terms(
    particles: np.ndarray, hypotheses: Hypotheses, model: MeasurementModel, vlad_best: float
) -> tuple[np.ndarray, float]:
    """The mixture's log terms (P, H') of ``model`` (pose error plus retrieval vector; H'
    leaves the joint poses out unless the model weighs them), and the smallest squared
    Mahalanobis distance of the "lost" signal."""
    quality = model.quality if model.covariance == "quality" else None
    if quality is None or not hypotheses.has_quality:
        quality = None
        per_entry = hypotheses.without_joint()
        hypotheses = per_entry if len(per_entry) else hypotheses
    pnp = model.pnp if model.covariance == "pnp" and quality is None else None
    if pnp is not None and hypotheses.pose_covariance is None:
        pnp = None  # an old server: the paper's covariance
    # Work column by column on (P, H) arrays: with 3- and 4-vectors this beats batched
    # matmuls by a wide margin (see bench/filter.py).
    X, Y, psi = (particles[:, k : k + 1] for k in range(3))
    # Component: N(x; z_i + mu1, s_i Sigma1), residual x - (z_i + mu1), wrapped heading.
    mu1 = model.mu1 if quality is None else quality.mu1
    centres = model.corrected(hypotheses, mu1)  # (H, 3)
    r1 = [X - centres[:, 0], Y - centres[:, 1], _wrap_residual(psi - centres[:, 2])]
    if model.retrieval_frame == "vehicle":
        # the pose error along / across the hypothesis's heading (Sigma1's axes)
        cos_h, sin_h = np.cos(hypotheses.pose_world[:, 2]), np.sin(hypotheses.pose_world[:, 2])
        r1[0], r1[1] = cos_h * r1[0] + sin_h * r1[1], cos_h * r1[1] - sin_h * r1[0]
    if pnp is not None:
        terms, maha1 = _pnp_terms(X, Y, psi, hypotheses, r1, model, pnp)
    elif quality is None:
        maha1 = _mahalanobis(r1, model._whiten1)
        terms = model.paper_log_density(maha1)
    else:
        log_scale = quality.log_scale(hypotheses)  # (H,)
        maha_unscaled = _mahalanobis(r1, quality._whiten)
        terms = quality.component_log_density(maha_unscaled, log_scale)
        # distance under the mixture's covariance (its second moment), so the "lost"
        # threshold means the same with or without the tail
        maha1 = maha_unscaled * np.exp(-log_scale) / quality.spread()
    closest = float(maha1.min())
    # Weight: N(e_i(x); mu2, Sigma2), e_i(x) = [e_vlad, X_i - X, Y_i - Y, psi_i - psi]
    # (world) or with the offset turned into the particle's frame (vehicle).
    entries = hypotheses.entry_pose_world
    if model.retrieval_frame == "world":
        offset = [entries[:, 0] - model.mu2[1] - X, entries[:, 1] - model.mu2[2] - Y]
    else:
        dx, dy = entries[:, 0] - X, entries[:, 1] - Y
        cos_psi, sin_psi = np.cos(psi), np.sin(psi)
        offset = [
            cos_psi * dx + sin_psi * dy - model.mu2[1],
            cos_psi * dy - sin_psi * dx - model.mu2[2],
        ]
    heading = _wrap_residual(entries[:, 2] - model.mu2[3] - psi)
    if model.vlad_evidence == "relative":
        mean_rel, std_rel = model.relative_vlad
        z_rel = (hypotheses.e_vlad - vlad_best - mean_rel) / std_rel  # (H,), per frame
        terms += model._log_norm2_relative - 0.5 * (
            z_rel * z_rel + _mahalanobis([*offset, heading], model._whiten2_offsets)
        )
        return terms, closest
    r2 = [np.broadcast_to(hypotheses.e_vlad - model.mu2[0], terms.shape), *offset, heading]
    terms += model._log_norm2 - 0.5 * _mahalanobis(r2, model._whiten2)
    return terms, closest


def _pnp_terms(X, Y, psi, hypotheses, r1_paper, model, pnp):
    """The PnP covariance model's pose terms (P, H) and the squared Mahalanobis distances
    (P, H) of the "lost" signal: (1 - w) N(x; z_i + mu1, S_i) + w paper(x) where the
    hypothesis has a covariance, the paper's density alone where not. The distance is the
    smaller of the two components' (with w > 0): a particle within the paper's Sigma1 of
    a hypothesis is not lost to it (S_i alone is so sharp in heading that a filter drifted
    by half a degree would find every right hypothesis unlikely and re-seed)."""
    maha_paper = _mahalanobis(r1_paper, model._whiten1)
    paper = model.paper_log_density(maha_paper)
    S, known = pnp.covariances(hypotheses.pose_covariance, model._pose_headings(hypotheses))
    if not known.any():
        return paper, maha_paper
    centres = model.corrected(hypotheses, pnp.mu1)
    r1 = [X - centres[:, 0], Y - centres[:, 1], _wrap_residual(psi - centres[:, 2])]
    maha = _mahalanobis_each(r1, np.linalg.inv(np.linalg.cholesky(S)))
    log_norm = -0.5 * (np.linalg.slogdet(S)[1] + 3.0 * math.log(2.0 * math.pi))
    own = log_norm - 0.5 * maha
    if pnp.outlier_weight > 0.0:
        own = np.logaddexp(
            own + math.log1p(-pnp.outlier_weight), paper + math.log(pnp.outlier_weight)
        )
        maha = np.minimum(maha, maha_paper)
    return np.where(known, own, paper), np.where(known, maha, maha_paper)


def _mahalanobis_each(residuals: list[np.ndarray], whiten: np.ndarray) -> np.ndarray:
    """|W_h r|^2 for residual components r_k (each (P, H)) and one lower-triangular
    W_h (H, 3, 3) per column h."""
    total = None
    for i in range(3):
        y = residuals[0] * whiten[:, i, 0]
        for k in range(1, i + 1):
            y = y + residuals[k] * whiten[:, i, k]
        total = y * y if total is None else total + y * y
    return total


def _mahalanobis(residuals: list[np.ndarray], whiten: np.ndarray) -> np.ndarray:
    """|W r|^2 for residual components r_k (each (P, H)) and lower-triangular W (D, D)."""
    total = None
    for row in range(len(residuals)):
        w = residuals[0] * whiten[row, 0]
        for col in range(1, row + 1):
            w = w + residuals[col] * whiten[row, col]
        total = w * w if total is None else total + w * w
    return total

"""Maximum-likelihood calibration of the measurement model (docs/method.md section 7).

From a training run that is not the test run: build a temporary map from every other
frame (``map_every``), query it with the remaining frames, and for each query take its k
closest map entries by planar pose distance (the paper's choice), run matching + PnP
against each (section 6 steps 3-5) and collect

    e_i   = z_q - z_i                                   (truth minus hypothesis)
    r_i   = [e_vlad_i, X_i - X_q, Y_i - Y_q, psi_i - psi_q]

then fit (mu1, Sigma1) to e and (mu2, Sigma2) to r with monoloc.core.calibration (monoloc's
default is the unbiased covariance about the mean). PnP is the localizer's own
(``server.localize.pose_hypotheses``: guided, plus the joint pose); (mu1, Sigma1) are
fitted on the per-entry hypotheses only, as in the paper, and the quality-aware model
(``QualityModel``: a covariance per hypothesis from its inliers, reprojection error and
joint flag) by maximum likelihood on every hypothesis, joint ones included. Hypotheses farther than
``gate_position_m`` / ``gate_yaw_rad`` from the truth are PnP failures, not noise: they
are counted and left out of both fits (the measurement model's outlier floor stands for
them), and reported. In the product's frame (``retrieval_frame`` "vehicle") e_i and the
offset of r_i are taken along and across the hypothesis's / the query's heading, and the
pose spreads' position parts (Sigma1, the PnP floor) are made isotropic.

Pure apart from the frames it is handed: no database, no files. Query frames are kept
as features + VLAD (not images), so a long training run fits in memory.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Sequence, Sized
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from monoloc.core.calibration import (
    PAPER_TAIL_SCALE,
    PAPER_TAIL_WEIGHT,
    PNP_FLOOR_STD_BOUNDS,
    PNP_PIXEL_STD_BOUNDS,
    fit_measurement_model,
    fit_pnp_covariance_model,
    fit_quality_model,
    fit_relative_vlad,
    gaussian_log_densities,
    paper_log_densities,
    pose_errors,
    retrieval_vectors,
)
from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import planar_from_T_world_from_cam, wrap_angle
from monoloc.core.measurement import (
    DEFAULT_COVARIANCE,
    DEFAULT_RETRIEVAL_FRAME,
    DEFAULT_VLAD_EVIDENCE,
    CovarianceModel,
    MeasurementModel,
    PnpCovarianceModel,
    RetrievalFrame,
    VladEvidence,
    to_heading_axes,
)
from monoloc.server.entry_builder import (
    BuildConfig,
    Source3d,
    TooFewPointsError,
    build_entry,
)
from monoloc.server.localize import PoseConfig, ReferenceEntry, pose_hypotheses
from monoloc.server.localize.frame import PoseStage
from monoloc.server.storage.records import NewEntry
from monoloc.server.vision.features import extract_features
from monoloc.server.vision.matching import MatchConfig, match_against_references
from monoloc.server.vision.vlad import compute_vlad
from monoloc.server.vision.vocabulary import Vocabulary

MIN_GOOD_HYPOTHESES = 10
_NO_COVARIANCE = np.full((3, 3), np.nan)
ERROR_CONVENTION = "e = truth - hypothesis, (X m, Y m, psi rad), psi wrapped to (-pi, pi]"
# How a fitted pose-error bias mu1 is kept (docs/notebook/transfer.md, 2026-12-02, h6):
# "none" as fitted; "james_stein" shrunk toward 0 by positive-part James-Stein on its
# standard error; "significance_gate" kept whole only beyond the chi-square(3) 95 %
# quantile, else 0; "along_only" (h7) its across-heading component zeroed, along and
# heading kept (a model fitted in the vehicle's axes only)
BiasShrinkage = Literal["none", "james_stein", "significance_gate", "along_only"]
# How the PnP term's floor is fitted in the product's frame (docs/notebook/transfer.md,
# 2026-12-02, h8): "half_trace" fits it along / across / heading, then gives both position
# axes half its trace (the third entry's isotropic floor); "isotropic_ml" fits mu1, the
# pixel std, one position floor and the heading floor by maximum likelihood in the form
# the model applies them (:func:`fit_isotropic_pnp`)
PnpFloorFit = Literal["half_trace", "isotropic_ml"]
# chi-square(3) quantile at 0.95: a whole-vector bias test at the 5 % level
CHI2_3_95 = 7.814727903251178


@dataclass(frozen=True)
class CalibrationConfig:
    """k: map entries per query (closest by pose); map_every: frames 0, m, 2m, ... build
    the temporary map, the others query it; gates: hypotheses farther from the truth are
    counted as outliers and left out of the fit; unbiased: covariance about the mean with
    N - 1 (monoloc) instead of the paper's mean(e e^T); poses / pose_stage: the pose
    stage as the localizer runs it (guided, joint pose, each pose's covariance);
    covariance: the model the stored calibration selects ("pnp" by default, "paper" or
    "quality"; all are fitted and stored, "pnp" when the pose stage gives the poses'
    covariances)."""

    k: int = 10
    map_every: int = 2
    gate_position_m: float = 3.0
    gate_yaw_rad: float = 0.2
    unbiased: bool = True
    # the training map lives in memory only: no entry images
    build: BuildConfig = field(default_factory=lambda: BuildConfig(image_max_side_px=0))
    match: MatchConfig = field(default_factory=MatchConfig)
    poses: PoseConfig = field(default_factory=PoseConfig)
    # the pose stage, the localizer's (bench/ passes a baseline's to compare)
    pose_stage: PoseStage = pose_hypotheses
    # the product's choices; bench/ sets the variants it measures (monoloc.core.measurement)
    covariance: CovarianceModel = DEFAULT_COVARIANCE
    retrieval_frame: RetrievalFrame = DEFAULT_RETRIEVAL_FRAME
    # how the retrieval term reads the VLAD distance (monoloc.core.measurement); the
    # relative one's (mean, std) is fitted and stored either way
    vlad_evidence: VladEvidence = DEFAULT_VLAD_EVIDENCE
    # the paper covariance's tail (monoloc.core.calibration.PAPER_TAIL_WEIGHT): set, not
    # fitted; tail_weight 0 stores the paper's single Gaussian
    tail_weight: float = PAPER_TAIL_WEIGHT
    tail_scale: float = PAPER_TAIL_SCALE
    # the fitted biases (the paper term's and the PnP term's mu1) kept as fitted, or
    # shrunk toward 0 as far as they are not significant (:func:`shrunk_bias`)
    bias_shrinkage: BiasShrinkage = "none"
    # how the PnP floor's position part is made isotropic (PnpFloorFit)
    pnp_floor_fit: PnpFloorFit = "half_trace"

    def __post_init__(self) -> None:
        if self.k < 1 or self.map_every < 2:
            raise InvalidInputError(
                f"calibration needs k >= 1 and map_every >= 2, got k={self.k}, "
                f"map_every={self.map_every}"
            )
        if not (self.gate_position_m > 0 and self.gate_yaw_rad > 0):
            raise InvalidInputError(f"calibration gates must be positive, got {self}")
        if self.pnp_floor_fit == "isotropic_ml" and self.retrieval_frame != "vehicle":
            raise InvalidInputError(
                "pnp_floor_fit 'isotropic_ml' fits the vehicle frame's isotropic floor: it "
                f"needs retrieval_frame 'vehicle', got {self.retrieval_frame!r}"
            )

    @property
    def min_frames(self) -> int:
        """The shortest run that yields k map frames and at least one query frame."""
        return self.map_every * (self.k - 1) + 2


def check_run_length(n_frames: int, config: CalibrationConfig, what: str) -> None:
    """InvalidInputError naming ``what`` when a run of ``n_frames`` is too short."""
    if n_frames < config.min_frames:
        raise InvalidInputError(
            f"{what} is too short to calibrate: {n_frames} frames; with k = {config.k} it "
            f"needs at least {config.min_frames} (k map entries, one every "
            f"{config.map_every} frames, queried by the frames between them)"
        )


@dataclass(frozen=True)
class TrainingFrame:
    """One frame of a training run: (H, W) uint8 grayscale image, true T_world_from_cam
    (4, 4) in the z-up world, and its 3D source (LiDAR scan, depth image or the right
    image of a stereo pair)."""

    image_gray: np.ndarray
    T_world_from_cam: np.ndarray
    source: Source3d


@dataclass(frozen=True)
class CalibrationResult:
    """The fitted model and how it was obtained (JSON-ready ``provenance``)."""

    model: MeasurementModel
    provenance: dict


@dataclass(frozen=True)
class _Query:
    keypoints_px: np.ndarray  # (N, 2) float32
    keypoint_scales: np.ndarray | None  # (N,) float32 pyramid scales, if PnP or covariance use them
    descriptors: np.ndarray  # (N, 32) uint8
    vlad: np.ndarray  # (2048,) float32
    truth_world: np.ndarray  # (3,) planar (X, Y, psi)


@dataclass
class CalibrationSamples:
    """Every hypothesis within the gates, one list item each (joint ones included, marked
    ``joint``): the query's true pose and its own index among the queries, the hypothesis
    and its entry's planar poses (X, Y, psi) and the entry's index in its run's temporary
    map, VLAD distance, inliers, reprojection error; plus the counts of the gated."""

    truth: list = field(default_factory=list)
    hypothesis: list = field(default_factory=list)
    e_vlad: list = field(default_factory=list)
    # the smallest VLAD distance among the sample's frame's hypotheses (gated ones too)
    e_vlad_best: list = field(default_factory=list)
    entry_pose: list = field(default_factory=list)
    n_inliers: list = field(default_factory=list)
    error_px: list = field(default_factory=list)
    joint: list = field(default_factory=list)
    # (3, 3) planar pose covariance at 1 px of each sample (NaN: none, e.g. a joint pose)
    pose_covariance: list = field(default_factory=list)
    query_index: list = field(default_factory=list)
    entry_index: list = field(default_factory=list)
    # VLAD distances between the training maps' entries VLAD_BAND_M apart (the fit check)
    neighbour_e_vlad: list = field(default_factory=list)
    n_hypotheses: int = 0
    n_joint: int = 0
    n_joint_gated: int = 0
    n_gated: int = 0
    n_queries_with_hypotheses: int = 0
    n_queries: int = 0


def _split_run(frames, intrinsics, vocabulary, config, tick):
    """Pass 1: map entries from every ``map_every``-th frame, features of the others."""
    entries: list[NewEntry] = []
    queries: list[_Query] = []
    n_frames = n_skipped = 0
    for i, frame in enumerate(frames):
        n_frames += 1
        if i % config.map_every == 0:
            try:
                entries.append(
                    build_entry(
                        frame.image_gray,
                        f"calibration-{i}",
                        frame.T_world_from_cam,
                        frame.source,
                        intrinsics,
                        vocabulary,
                        None,
                        config.build,
                    )
                )
            except TooFewPointsError:
                n_skipped += 1
        else:
            features = extract_features(
                frame.image_gray,
                config.build.orb,
                scales=True,
            )
            queries.append(
                _Query(
                    features.keypoints_px,
                    features.scales,
                    features.descriptors,
                    compute_vlad(features.descriptors, vocabulary),
                    planar_from_T_world_from_cam(np.asarray(frame.T_world_from_cam)),
                )
            )
        tick()
    return entries, queries, n_frames, n_skipped


def _query_samples(query, entries, entry_pose, intrinsics, config, rng, samples) -> None:
    """Pass 2 for one query: its k closest entries by position, matching, PnP (the
    localizer's, joint pose included), errors."""
    truth = query.truth_world
    dist_m = np.hypot(entry_pose[:, 0] - truth[0], entry_pose[:, 1] - truth[1])
    nearest = np.argsort(dist_m, kind="stable")[: config.k]
    refs = [
        ReferenceEntry(
            int(j), entries[j].T_world_from_cam, entries[j].descriptors, entries[j].points_cam
        )
        for j in nearest
    ]
    matches = match_against_references(
        query.descriptors, [r.descriptors for r in refs], config.match
    )
    e_vlad = {int(j): float(np.linalg.norm(entries[j].vlad - query.vlad)) for j in nearest}
    hypotheses, _ = config.pose_stage(
        query.keypoints_px,
        refs,
        matches,
        e_vlad,
        intrinsics,
        config.poses,
        rng,
        keypoint_scales=query.keypoint_scales,
        descriptors=query.descriptors,
    )
    vlad_best = min((h.e_vlad for h in hypotheses), default=math.nan)
    for h in hypotheses:
        samples.n_hypotheses += int(not h.joint)
        samples.n_joint += int(h.joint)
        e = truth - h.pose_world
        e[2] = wrap_angle(e[2])
        if np.hypot(e[0], e[1]) > config.gate_position_m or abs(e[2]) > config.gate_yaw_rad:
            samples.n_gated += int(not h.joint)
            samples.n_joint_gated += int(h.joint)
            continue
        samples.truth.append(truth)
        samples.hypothesis.append(h.pose_world)
        samples.e_vlad.append(h.e_vlad)
        samples.e_vlad_best.append(vlad_best)
        samples.entry_pose.append(h.entry_pose_world)
        samples.n_inliers.append(h.n_inliers)
        samples.error_px.append(h.reprojection_error_px)
        samples.joint.append(h.joint)
        samples.pose_covariance.append(
            _NO_COVARIANCE if h.covariance_px1 is None else h.covariance_px1
        )
        samples.query_index.append(samples.n_queries)
        samples.entry_index.append(-1 if h.joint else int(h.entry_id))
    samples.n_queries_with_hypotheses += int(bool(hypotheses))
    samples.n_queries += 1


def calibrate(
    frames: Iterable[TrainingFrame],
    intrinsics: CameraIntrinsics,
    vocabulary: Vocabulary,
    config: CalibrationConfig,
    rng: np.random.Generator,
    progress: Callable[[int, int], None] | None = None,
    n_frames: int | None = None,
    source_name: str = "",
) -> CalibrationResult:
    """Fit the measurement model on a training run (see the module docstring).

    ``progress(done, total)`` is called after every frame of each pass (total = frames +
    query frames); an exception it raises (a stop request) ends the calibration.
    ``n_frames`` (default: ``len(frames)`` when it has one) sizes the progress total.
    Raises InvalidInputError when the run is too short or yields too few good hypotheses.
    """
    run = TrainingRun(frames, source_name, n_frames)
    return calibrate_runs([run], intrinsics, vocabulary, config, rng, progress)


@dataclass(frozen=True)
class TrainingRun:
    """One training run: its frames (read once, in order), a name for messages and the
    provenance, and its length when known (sizes the progress total)."""

    frames: Iterable[TrainingFrame]
    name: str = ""
    n_frames: int | None = None


def calibrate_runs(
    runs: Sequence[TrainingRun],
    intrinsics: CameraIntrinsics,
    vocabulary: Vocabulary,
    config: CalibrationConfig,
    rng: np.random.Generator,
    progress: Callable[[int, int], None] | None = None,
) -> CalibrationResult:
    """Fit the measurement model on the pooled error samples of several training runs
    (e.g. the same district by day and by night). Each run is split into its own
    temporary map and queries (a run's queries meet only its own map: day queries are
    not matched against night entries), then one fit covers every sample, so the
    quality-aware model sees hypotheses from both good and poor images. ``progress`` as
    in :func:`calibrate`, over all runs."""
    samples, per_run = collect_samples(runs, intrinsics, vocabulary, config, rng, progress)
    return fit_samples(samples, per_run, [run.name for run in runs], config, vocabulary)


def fit_samples(
    samples: CalibrationSamples,
    per_run: list[dict],
    names: Sequence[str],
    config: CalibrationConfig,
    vocabulary: Vocabulary,
) -> CalibrationResult:
    """The measurement model fitted on samples :func:`collect_samples` gathered from the
    runs ``names`` (their counts ``per_run``): the fit alone, so bench/ can fit several
    configurations on one run's samples."""
    what = " + ".join(name or "the training run" for name in names)
    joint = np.array(samples.joint, dtype=bool)
    used = int((~joint).sum())
    n_queries = sum(c["query_frames"] for c in per_run)
    if used < MIN_GOOD_HYPOTHESES:
        raise InvalidInputError(
            f"calibration of {what} found only {used} good hypotheses ({samples.n_hypotheses} "
            f"accepted by PnP, {samples.n_gated} beyond the gates) from {n_queries} query "
            f"frames; it needs {MIN_GOOD_HYPOTHESES}: the run is too short or its images do "
            "not match each other"
        )
    truth = np.array(samples.truth)
    hypothesis = np.array(samples.hypothesis)
    covariances = np.array(samples.pose_covariance).reshape(-1, 3, 3)
    errors = pose_errors(truth, hypothesis)
    if config.retrieval_frame == "vehicle":
        # the pose error along / across the hypothesis's heading, as the model reads it
        errors, covariances = to_heading_axes(errors, hypothesis[:, 2], covariances)
    paper = fit_measurement_model(
        errors[~joint],
        retrieval_vectors(
            np.array(samples.e_vlad)[~joint],
            np.array(samples.entry_pose)[~joint],
            truth[~joint],
            config.retrieval_frame,
        ),
        unbiased=config.unbiased,
        source="calibrated",
        retrieval_frame=config.retrieval_frame,
        tail_weight=config.tail_weight,
        tail_scale=config.tail_scale,
    )
    quality = fit_quality_model(
        errors, np.array(samples.n_inliers), np.array(samples.error_px), joint
    )
    pnp = _fit_pnp(errors[~joint], covariances[~joint], paper, config)
    if pnp is not None and config.pnp_floor_fit == "isotropic_ml":
        pnp = fit_isotropic_pnp(errors[~joint], covariances[~joint], paper, pnp)
    if config.covariance == "pnp" and pnp is None:
        raise InvalidInputError(
            f"calibration of {what} cannot fit the pnp covariance model: fewer than "
            f"{MIN_GOOD_HYPOTHESES} hypotheses with a pose covariance (the pose stage must "
            "give them)"
        )
    if config.bias_shrinkage == "along_only" and config.retrieval_frame != "vehicle":
        raise InvalidInputError(
            "bias_shrinkage 'along_only' reads mu1 along / across the heading: it needs "
            f"retrieval_frame 'vehicle', got {config.retrieval_frame!r}"
        )
    if config.bias_shrinkage != "none":
        paper, pnp = _shrunk_biases(errors[~joint], paper, pnp, config.bias_shrinkage)
    if config.retrieval_frame == "vehicle":
        paper, pnp = _isotropic_pose_spread(paper, pnp)
    relative = np.array(samples.e_vlad)[~joint] - np.array(samples.e_vlad_best)[~joint]
    model = dataclasses.replace(
        paper,
        quality=quality,
        pnp=pnp,
        covariance=config.covariance,
        vlad_evidence=config.vlad_evidence,
        relative_vlad=fit_relative_vlad(relative, config.unbiased),
    )
    counts = {key: sum(c[key] for c in per_run) for key in per_run[0] if key != "used"}
    provenance = _provenance(" + ".join(names), counts, samples, config, vocabulary)
    if len(names) > 1:
        provenance["runs"] = [{"source": n, **c} for n, c in zip(names, per_run, strict=True)]
    return CalibrationResult(model, provenance)


def bias_z_squared(mean: np.ndarray, standard_error_cov: np.ndarray) -> float:
    """mu^T SE^-1 mu: the squared Mahalanobis length of a mean (D,) under its standard
    error covariance (D, D) (the samples' covariance / n)."""
    mean = np.asarray(mean, dtype=np.float64)
    return float(mean @ np.linalg.solve(np.asarray(standard_error_cov, np.float64), mean))


def shrunk_bias(
    mean: np.ndarray, standard_error_cov: np.ndarray, method: BiasShrinkage = "james_stein"
) -> np.ndarray:
    """A fitted bias (D,) kept only as far as it is significant, its direction unchanged.

    ``standard_error_cov`` (D, D) is the mean's standard error covariance (the samples'
    covariance / n). "james_stein": positive-part James-Stein toward 0,
    max(0, 1 - (D - 2) / z^2) mu with z^2 = mu^T SE^-1 mu (D >= 3); "significance_gate":
    mu if z^2 > the chi-square(3) 95 % quantile, else 0 (D = 3); "along_only": mu in the
    heading axes (along, across, heading) with its across component 0, whatever its
    significance (an across bias is set by the side the training road's facades stand
    on; docs/notebook/transfer.md, h6 / h7); "none": mu.
    """
    mean = np.asarray(mean, dtype=np.float64)
    if method == "none":
        return mean.copy()
    if method == "along_only":
        if len(mean) != 3:
            raise InvalidInputError(f"along_only needs (along, across, heading), got {len(mean)}")
        return mean * np.array([1.0, 0.0, 1.0])
    z2 = bias_z_squared(mean, standard_error_cov)
    if method == "james_stein":
        if len(mean) < 3:
            raise InvalidInputError(f"James-Stein shrinkage needs D >= 3, got {len(mean)}")
        factor = max(0.0, 1.0 - (len(mean) - 2) / z2) if z2 > 0 else 0.0
        return factor * mean
    if method == "significance_gate":
        if len(mean) != 3:
            raise InvalidInputError(f"the chi-square(3) gate needs D = 3, got {len(mean)}")
        return mean.copy() if z2 > CHI2_3_95 else np.zeros_like(mean)
    raise InvalidInputError(f"unknown bias shrinkage {method!r}")


def bias_standard_error(errors: np.ndarray) -> np.ndarray:
    """The standard error covariance (3, 3) of the mean of pose errors (N, 3): their
    unbiased covariance / N (the per-entry samples are close to independent here:
    docs/notebook/transfer.md, 2026-12-02, h5)."""
    errors = np.asarray(errors, dtype=np.float64)
    return np.cov(errors, rowvar=False) / len(errors)


def _shrunk_biases(errors: np.ndarray, paper: MeasurementModel, pnp, method: BiasShrinkage):
    """The paper term's and the PnP term's mu1 shrunk by :func:`shrunk_bias`, both on the
    standard error of the per-entry errors' mean (N, 3) they were fitted on."""
    se = bias_standard_error(errors)
    paper = dataclasses.replace(paper, mu1=shrunk_bias(paper.mu1, se, method))
    if pnp is not None:
        pnp = dataclasses.replace(pnp, mu1=shrunk_bias(pnp.mu1, se, method))
    return paper, pnp


def _isotropic_position(cov: np.ndarray) -> np.ndarray:
    """A (3, 3) pose covariance with its position block isotropic (half its trace on
    both axes) and uncorrelated with the heading."""
    out = np.diag(np.diag(cov)).astype(np.float64)
    out[0, 0] = out[1, 1] = 0.5 * (cov[0, 0] + cov[1, 1])
    return out


def _isotropic_pose_spread(paper: MeasurementModel, pnp):
    """The paper term's Sigma1 and the PnP floor with isotropic position spreads (the bias
    mu1 kept along / across the heading): the direction of a pose error is what each
    hypothesis's own PnP covariance says; the training road's split of the rest between
    along and across did not transfer to other streets (docs/notebook/transfer.md,
    2026-12-02, third entry)."""
    paper = dataclasses.replace(paper, Sigma1=_isotropic_position(paper.Sigma1))
    if pnp is not None:
        pnp = dataclasses.replace(pnp, floor=_isotropic_position(pnp.floor))
    return paper, pnp


def fit_isotropic_pnp(
    errors: np.ndarray,
    covariances: np.ndarray,
    outliers: MeasurementModel,
    start: PnpCovarianceModel,
) -> PnpCovarianceModel:
    """The PnP term refitted by maximum likelihood with its floor in the form the vehicle
    frame applies it: diag(f^2, f^2, h^2), one position floor f on both axes and the
    heading floor h, together with mu1 and the pixel std (errors (N, 3) and covariances
    (N, 3, 3) along / across / heading, NaN covariances left out; ``outliers`` the paper
    term, mixed in with ``start.outlier_weight`` as in the fit of ``start``).

    Why not half the trace of the along / across fit: on a straight road the across and
    heading errors are two readings of one ambiguity, and that fit may put all of it into
    the across floor, which the average then carries onto both axes
    (docs/notebook/transfer.md, 2026-12-02, h8). Started from ``start`` and from a few
    floors; the likeliest is kept."""
    from scipy.optimize import minimize

    e = np.asarray(errors, dtype=np.float64)
    C = np.asarray(covariances, dtype=np.float64).reshape(-1, 3, 3)
    known = np.isfinite(C).all(axis=(1, 2)) & np.isfinite(e).all(axis=1)
    e, C = e[known], C[known]
    w = start.outlier_weight
    outlier = paper_log_densities(e, outliers) + math.log(w) if w > 0 else None

    def nll(theta: np.ndarray) -> float:
        f2, h2 = math.exp(2.0 * theta[4]), math.exp(2.0 * theta[5])
        own = gaussian_log_densities(
            e - theta[:3], math.exp(2.0 * theta[3]) * C + np.diag([f2, f2, h2])
        )
        if outlier is None:
            return -float(own.sum())
        return -float(np.logaddexp(own + math.log1p(-w), outlier).sum())

    (f_lo, f_hi), _, (h_lo, h_hi) = PNP_FLOOR_STD_BOUNDS
    bounds = [(None, None)] * 3 + [
        tuple(np.log(PNP_PIXEL_STD_BOUNDS)),
        (math.log(f_lo), math.log(f_hi)),
        (math.log(h_lo), math.log(h_hi)),
    ]
    half_trace = math.sqrt(0.5 * (start.floor[0, 0] + start.floor[1, 1]))
    heading = math.sqrt(start.floor[2, 2])
    starts = [(half_trace, heading)] + [(f, h) for f in (1e-3, 1e-2) for h in (1e-4, 1e-3)]
    best = None
    for f0, h0 in starts:
        theta0 = np.concatenate(
            [start.mu1, [math.log(start.pixel_std_px)], np.log(np.clip([f0, h0], 1e-5, 1.0))]
        )
        theta0[4] = float(np.clip(theta0[4], *bounds[4]))
        theta0[5] = float(np.clip(theta0[5], *bounds[5]))
        result = minimize(nll, theta0, method="L-BFGS-B", bounds=bounds)
        if best is None or result.fun < best.fun:
            best = result
    theta = best.x
    f2, h2 = math.exp(2.0 * theta[4]), math.exp(2.0 * theta[5])
    return dataclasses.replace(
        start,
        mu1=theta[:3].copy(),
        pixel_std_px=math.exp(theta[3]),
        floor=np.diag([f2, f2, h2]),
    )


def _fit_pnp(errors: np.ndarray, covariances: np.ndarray, paper, config: CalibrationConfig):
    """The PnP covariance model fitted on the per-entry samples with a covariance, the
    ``paper`` model (fitted on the same samples) its outliers' density with the paper
    tail's weight; None with fewer than ``MIN_GOOD_HYPOTHESES`` such samples."""
    covariances = covariances.reshape(-1, 3, 3)
    if int(np.isfinite(covariances).all(axis=(1, 2)).sum()) < MIN_GOOD_HYPOTHESES:
        return None
    return fit_pnp_covariance_model(errors, covariances, paper, config.tail_weight)


def collect_samples(
    runs: Sequence[TrainingRun],
    intrinsics: CameraIntrinsics,
    vocabulary: Vocabulary,
    config: CalibrationConfig,
    rng: np.random.Generator,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[CalibrationSamples, list[dict]]:
    """The error samples calibration fits, and each run's frame counts: each run split
    into its own temporary map and queries, every query's k closest entries matched and
    solved by ``config.pose_stage``. Also for comparing pose stages on the same run
    (bench/pnp_calibration.py)."""
    if not runs:
        raise InvalidInputError("calibration needs at least one training run")
    totals = []
    for run in runs:
        n = run.n_frames
        if n is None and isinstance(run.frames, Sized):
            n = len(run.frames)
        totals.append(n or 0)
    planned = [n + n - math.ceil(n / config.map_every) for n in totals]
    ticker = _Ticker(progress, sum(planned))
    samples = CalibrationSamples()
    per_run = []
    for run, plan in zip(runs, planned, strict=True):
        counts = _run_samples(run, intrinsics, vocabulary, config, rng, ticker, samples)
        # the run's true length is known now: correct the total for it
        ticker.total += counts["frames"] + counts["query_frames"] - plan
        per_run.append(counts)
    return samples, per_run


def _run_samples(run, intrinsics, vocabulary, config, rng, ticker, samples) -> dict:
    """Both passes over one training run: its temporary map, its queries' samples added
    to ``samples``; the run's frame counts."""
    entries, queries, seen, skipped = _split_run(
        run.frames, intrinsics, vocabulary, config, ticker.tick
    )
    what = run.name or "the training run"
    if len(entries) < config.k or not queries:
        raise InvalidInputError(
            f"calibration of {what} needs at least {config.k} map frames with 3D points and "
            f"some query frames (at least {config.min_frames} frames); got {len(entries)} map "
            f"frames ({skipped} without enough 3D points) and {len(queries)} query frames "
            f"from {seen} frames"
        )
    entry_pose = np.array([planar_from_T_world_from_cam(e.T_world_from_cam) for e in entries])
    vlads = np.stack([e.vlad for e in entries])
    samples.neighbour_e_vlad.extend(
        neighbour_vlad_distances(entry_pose, lambda rows: vlads[rows]).tolist()
    )
    before = samples.n_queries_with_hypotheses
    used_before = len(samples.joint) - int(np.sum(samples.joint))
    for query in queries:
        _query_samples(query, entries, entry_pose, intrinsics, config, rng, samples)
        ticker.tick()
    return {
        "frames": seen,
        "map_frames": len(entries),
        "map_frames_skipped": skipped,
        "query_frames": len(queries),
        "queries_with_hypotheses": samples.n_queries_with_hypotheses - before,
        "used": len(samples.joint) - int(np.sum(samples.joint)) - used_before,
    }


class _Ticker:
    """Counts finished frames and reports ``progress(done, total)``."""

    def __init__(self, progress: Callable[[int, int], None] | None, total: int) -> None:
        self.progress, self.total, self.done = progress, total, 0

    def tick(self) -> None:
        self.done += 1
        if self.progress is not None:
            self.progress(self.done, max(self.total, self.done))


# Entries this far apart (m, planar) give the VLAD distances a map is described by: the
# span of a query and the entries it matches, at any mapping density.
VLAD_BAND_M = (2.0, 6.0)
VLAD_FIT_MAX_ENTRIES = 1000


def neighbour_vlad_distances(
    poses_world: np.ndarray,
    vlads_at: Callable[[np.ndarray], np.ndarray],
    band_m: tuple[float, float] = VLAD_BAND_M,
    max_entries: int = VLAD_FIT_MAX_ENTRIES,
    seed: int = 0,
) -> np.ndarray:
    """VLAD distances (M,) between map entries whose planar positions lie ``band_m``
    apart: for up to ``max_entries`` entries (a seeded sample of larger maps), to each
    other entry in the band. ``poses_world`` (N, 3); ``vlads_at(rows)`` -> (R, D) VLADs."""
    from scipy.spatial import cKDTree

    poses = np.asarray(poses_world, dtype=np.float64).reshape(-1, 3)
    if len(poses) < 2:
        return np.zeros(0)
    rng = np.random.default_rng(seed)
    rows = np.arange(len(poses))
    if len(rows) > max_entries:
        rows = np.sort(rng.choice(rows, max_entries, replace=False))
    tree = cKDTree(poses[:, :2])
    lo, hi = band_m
    pairs = [
        (i, j)
        for i, near in zip(rows, tree.query_ball_point(poses[rows, :2], hi), strict=True)
        for j in near
        if j != i and np.hypot(*(poses[j, :2] - poses[i, :2])) >= lo
    ]
    if not pairs:
        return np.zeros(0)
    first, second = np.array(pairs).T
    needed, inverse = np.unique(np.concatenate([first, second]), return_inverse=True)
    vlads = np.asarray(vlads_at(needed), dtype=np.float64)
    a, b = vlads[inverse[: len(first)]], vlads[inverse[len(first) :]]
    return np.linalg.norm(a - b, axis=1)


def vlad_statistics(distances: np.ndarray) -> dict[str, Any]:
    """Mean, std and count of VLAD distances, as stored in a calibration's provenance."""
    d = np.asarray(distances, dtype=np.float64)
    return {
        "band_m": list(VLAD_BAND_M),
        "mean": float(d.mean()) if len(d) else None,
        "std": float(d.std(ddof=1)) if len(d) > 1 else None,
        "n": int(len(d)),
    }


def calibration_fit(provenance: dict[str, Any], map_distances: np.ndarray) -> dict[str, Any]:
    """How a calibration matches the map it is applied to: the VLAD distances between the
    map's entries ``VLAD_BAND_M`` apart against those of the calibration's training maps
    (``provenance["vlad_neighbours"]``), the shift in the training spread, and a warning
    when it exceeds one spread (the calibration's VLAD term then weighs this map's
    hypotheses as it never saw them: docs/method.md section 7)."""
    training = provenance.get("vlad_neighbours") or {}
    here = vlad_statistics(map_distances)
    fit: dict[str, Any] = {"training": training or None, "map": here}
    if training.get("mean") is None or not training.get("std") or here["mean"] is None:
        fit.update(shift_in_training_std=None, fits=None, warning=None)
        return fit
    shift = (here["mean"] - training["mean"]) / training["std"]
    fits = abs(shift) <= 1.0
    fit.update(
        shift_in_training_std=float(shift),
        fits=bool(fits),
        warning=None
        if fits
        else (
            f"this map's VLAD distances ({here['mean']:.3f} +- {here['std'] or 0:.3f} between "
            f"entries {VLAD_BAND_M[0]:g}-{VLAD_BAND_M[1]:g} m apart) lie {shift:+.1f} training "
            f"spreads from the calibration run's ({training['mean']:.3f} +- "
            f"{training['std']:.3f}): calibrate on a run that looks like this map's streets"
        ),
    )
    return fit


def _has_covariances(samples: CalibrationSamples) -> bool:
    covariances = np.asarray(samples.pose_covariance, dtype=np.float64)
    return bool(covariances.size) and bool(np.isfinite(covariances).any())


def _provenance(source_name, counts, samples: CalibrationSamples, config, vocabulary) -> dict:
    return {
        "source": source_name,
        **counts,
        "hypotheses": samples.n_hypotheses,
        "used": len(samples.truth) - int(np.sum(samples.joint)),
        "joint_hypotheses": samples.n_joint,
        "joint_used": int(np.sum(samples.joint)),
        "joint_gated_outliers": samples.n_joint_gated,
        "gated_outliers": samples.n_gated,
        "vlad_neighbours": vlad_statistics(np.array(samples.neighbour_e_vlad)),
        "pnp": "guided"
        if config.pose_stage is pose_hypotheses
        else (config.pose_stage.__doc__ or config.pose_stage.__name__).split("\n")[0],
        "quality_model": "ML: (1 - eps) N(mu1, s Sigma1) + eps N(mu1, kappa^2 s Sigma1), "
        "log s = beta . [log(n_inliers / n_ref), log(reprojection_error / error_ref), joint]",
        "pnp_model": "ML: (1 - w) N(mu1, sigma_px^2 C + diag(floor)) + w paper, C the "
        "pose's covariance from its own inliers at 1 px, paper the paper covariance's "
        "density (outliers), w the paper tail's weight"
        if _has_covariances(samples)
        else "none (the pose stage gives no pose covariances)",
        "k": config.k,
        "map_every": config.map_every,
        "gate_position_m": config.gate_position_m,
        "gate_yaw_rad": config.gate_yaw_rad,
        "covariance": "unbiased about the mean (N - 1)"
        if config.unbiased
        else "paper: mean(e e^T) about zero",
        "paper_tail": (
            f"set, not fitted: (1 - {config.tail_weight:g}) N(mu1, Sigma1) + "
            f"{config.tail_weight:g} N(mu1, {config.tail_scale:g}^2 Sigma1)"
            if config.tail_weight > 0
            else "none (the paper's single Gaussian)"
        ),
        "error_convention": ERROR_CONVENTION,
        "vocabulary_hash": vocabulary.version,
    }

"""Maximum-likelihood calibration of the measurement model (METHOD.md section 7).

From a training run that is not the test run: build a temporary map from every other
frame, query it with the remaining frames, and for each query take its k closest map
entries by planar pose distance (the paper's choice), run matching + PnP against each
(section 6 steps 3-5) and collect

    e_i   = z_q - z_i                                   (truth minus hypothesis)
    r_i   = [e_vlad_i, X_i - X_q, Y_i - Y_q, psi_i - psi_q]

then fit (mu1, Sigma1) to e and (mu2, Sigma2) to r with client.calibration (monoloc's
default is the unbiased covariance about the mean). Hypotheses farther than
``gate_position_m`` from the truth are PnP failures, not noise: they are counted and left
out of Sigma1 (the measurement model's outlier floor stands for them), and reported.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from client.calibration import fit_measurement_model, pose_errors, retrieval_vectors
from client.camera import CameraIntrinsics
from client.errors import InvalidInputError
from client.geometry import planar_from_T_world_from_cam, wrap_angle
from client.measurement import MeasurementModel
from server.entry_builder import (
    BuildConfig,
    DepthSource,
    LidarSource,
    TooFewPointsError,
    build_entry,
)
from server.vision.features import extract_features
from server.vision.hypothesis import compose_hypothesis
from server.vision.matching import MatchConfig, match_against_references
from server.vision.pnp import PnpConfig, estimate_relative_pose
from server.vision.vlad import compute_vlad
from server.vision.vocabulary import Vocabulary


@dataclass(frozen=True)
class CalibrationConfig:
    k: int = 10
    map_every: int = 2  # frames 0, 2, 4, ... build the map; the others query it
    gate_position_m: float = 3.0
    gate_yaw_rad: float = 0.2
    unbiased: bool = True
    build: BuildConfig = field(default_factory=BuildConfig)
    match: MatchConfig = field(default_factory=MatchConfig)
    pnp: PnpConfig = field(default_factory=PnpConfig)


@dataclass(frozen=True)
class TrainingFrame:
    """One frame of a training run: grayscale image, true pose, 3D source."""

    image_gray: np.ndarray
    T_world_from_cam: np.ndarray
    source: LidarSource | DepthSource


@dataclass(frozen=True)
class CalibrationResult:
    model: MeasurementModel
    provenance: dict


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
    """Fit the measurement model on a training run (see the module docstring)."""
    map_entries, queries = [], []
    for i, frame in enumerate(frames):
        if i % config.map_every == 0:
            try:
                entry = build_entry(
                    frame.image_gray,
                    f"calib-{i}",
                    frame.T_world_from_cam,
                    frame.source,
                    intrinsics,
                    vocabulary,
                    None,
                    config.build,
                )
            except TooFewPointsError:
                continue
            map_entries.append(entry)
        else:
            queries.append((frame.image_gray, np.asarray(frame.T_world_from_cam)))
        if progress and n_frames:
            progress(i + 1, 2 * n_frames)
    if len(map_entries) < config.k or not queries:
        raise InvalidInputError(
            f"calibration needs at least {config.k} map frames and some query frames; "
            f"got {len(map_entries)} and {len(queries)}"
        )
    entry_planar = np.array([planar_from_T_world_from_cam(e.T_world_from_cam) for e in map_entries])
    errors, retrieval, n_hyp, n_gated = [], [], 0, 0
    for qi, (image, T_true) in enumerate(queries):
        truth = planar_from_T_world_from_cam(T_true)
        features = extract_features(image, config.build.orb)
        vlad_q = compute_vlad(features.descriptors, vocabulary)
        dist = np.hypot(entry_planar[:, 0] - truth[0], entry_planar[:, 1] - truth[1])
        nearest = np.argsort(dist)[: config.k]
        refs = [map_entries[j] for j in nearest]
        matches = match_against_references(
            features.descriptors, [r.descriptors for r in refs], config.match
        )
        for j, ref, pairs in zip(nearest, refs, matches, strict=True):
            rel = estimate_relative_pose(
                features.keypoints_px[pairs[:, 0]],
                ref.points_cam[pairs[:, 1]],
                intrinsics,
                config.pnp,
                rng,
            )
            if not rel.accepted:
                continue
            n_hyp += 1
            z = planar_from_T_world_from_cam(
                compose_hypothesis(ref.T_world_from_cam, rel.T_ref_from_query)
            )
            e = truth - z
            e[2] = wrap_angle(e[2])
            if np.hypot(e[0], e[1]) > config.gate_position_m or abs(e[2]) > config.gate_yaw_rad:
                n_gated += 1
                continue
            errors.append((truth, z))
            e_vlad = float(np.linalg.norm(ref.vlad - vlad_q))
            retrieval.append((e_vlad, entry_planar[j], truth))
        if progress and n_frames:
            progress(n_frames + qi + 1, 2 * n_frames)
    if len(errors) < 10:
        raise InvalidInputError(
            f"calibration found only {len(errors)} good hypotheses; the training run is too "
            "short or does not match its own frames"
        )
    truth_arr = np.array([t for t, _ in errors])
    hyp_arr = np.array([z for _, z in errors])
    r_vlad = np.array([r[0] for r in retrieval])
    r_entry = np.array([r[1] for r in retrieval])
    r_truth = np.array([r[2] for r in retrieval])
    model = fit_measurement_model(
        pose_errors(truth_arr, hyp_arr),
        retrieval_vectors(r_vlad, r_entry, r_truth),
        unbiased=config.unbiased,
        source="calibrated",
    )
    provenance = {
        "source": source_name,
        "map_frames": len(map_entries),
        "query_frames": len(queries),
        "hypotheses": n_hyp,
        "used": len(errors),
        "gated_outliers": n_gated,
        "k": config.k,
        "covariance": "unbiased about the mean" if config.unbiased else "paper: mean(e e^T)",
        "vocabulary": vocabulary.version,
    }
    return CalibrationResult(model, provenance)

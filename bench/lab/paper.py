"""The paper-faithful pipeline, a baseline behind the localization stage's interfaces
(``monoloc.server.localize.frame.FrameStages``): exact float k-NN over every VLAD of
the index (no Hamming shortlist; with a prior, over every entry inside it), OpenCV
brute-force Hamming matching per reference (the same match rule), and every retrieved
entry solved by its own PnP RANSAC (docs/method.md section 6), without guided PnP,
refit by projection, pose covariances or poses of several entries. Features, VLAD and
the hypotheses' form are the product's.

    localize_frame(..., stages=PAPER_STAGES)
    InProcessLocalizer(..., stages=PAPER_STAGES)
    CalibrationConfig(pose_stage=independent_pose_hypotheses)
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.geometry import planar_from_T_world_from_cam
from monoloc.core.prior import RetrievalPrior
from monoloc.server.index.retrieval import RetrievalIndex, SearchResult
from monoloc.server.localize import PoseConfig, PoseHypothesis, ReferenceEntry
from monoloc.server.localize.frame import FrameStages
from monoloc.server.vision.matching import match_against_references_bruteforce
from monoloc.server.vision.pnp import estimate_relative_pose


def retrieve_exhaustive(
    index: RetrievalIndex,
    vlad: np.ndarray,
    code: np.ndarray,
    k: int,
    prior: RetrievalPrior | None,
) -> SearchResult:
    """Top-k by exact float VLAD distance over every entry: the index ranks them all."""
    found = index.search(vlad, code, max(len(index), 1), prior)
    return SearchResult(found.entry_ids[:k], found.distances[:k])


def independent_pose_hypotheses(
    keypoints_px: np.ndarray,
    refs: Sequence[ReferenceEntry],
    matches: Sequence[np.ndarray],
    e_vlad: dict[int, float],
    intrinsics: CameraIntrinsics,
    config: PoseConfig,
    rng: np.random.Generator,
    prior: RetrievalPrior | None = None,
    keypoint_scales: np.ndarray | None = None,
    descriptors: np.ndarray | None = None,
) -> tuple[list[PoseHypothesis], list[tuple[int, str]]]:
    """Independent PnP RANSAC per entry (the paper's pose stage).

    The pose stage's signature; only ``config.pnp`` is used: no covariances, no poses of
    several entries."""
    keypoints_px = np.asarray(keypoints_px, dtype=np.float64)
    hypotheses: list[PoseHypothesis] = []
    rejected: list[tuple[int, str]] = []
    for ref, pairs in zip(refs, matches, strict=True):
        rel = estimate_relative_pose(
            keypoints_px[pairs[:, 0]], ref.points_cam[pairs[:, 1]], intrinsics, config.pnp, rng
        )
        if not rel.accepted:
            rejected.append((ref.entry_id, rel.reject_reason or "rejected"))
            continue
        T_world_from_query = np.asarray(ref.T_world_from_cam, dtype=np.float64) @ (
            rel.T_ref_from_query
        )
        hypotheses.append(
            PoseHypothesis(
                entry_id=ref.entry_id,
                T_world_from_cam=T_world_from_query,
                pose_world=planar_from_T_world_from_cam(T_world_from_query),
                entry_pose_world=ref.pose_world,
                e_vlad=float(e_vlad[ref.entry_id]),
                n_matches=len(pairs),
                n_inliers=rel.n_inliers,
                reprojection_error_px=rel.reprojection_error_px,
                method=rel.method,
                entry_tags=ref.tags,
            )
        )
    return hypotheses, rejected


PAPER_STAGES = FrameStages(
    retrieve=retrieve_exhaustive,
    match=match_against_references_bruteforce,
    poses=independent_pose_hypotheses,
)

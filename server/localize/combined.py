"""Poses of several entries of one frame: the joint pose of the consistent entries, the
pooled pose of a frame whose entries gave none of their own, and the alternative pose of
a frame whose entries agree on a poorly pinned pose (``vision.joint``)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.geometry import invert_rigid, planar_from_T_world_from_cam
from monoloc.server.localize.config import PoseConfig
from monoloc.server.localize.results import PoseHypothesis, ReferenceEntry
from monoloc.server.vision.joint import (
    EntryInliers,
    JointConfig,
    consistent_group,
    estimate_pooled_pose,
    joint_pose_from_best_start,
)
from monoloc.server.vision.pnp import PnpConfig, within_threshold
from monoloc.server.vision.pose_covariance import planar_pose_covariance, position_spread_m
from monoloc.server.vision.projection import KeypointGrid, match_by_projection


def joint_hypothesis(
    hypotheses: Sequence[PoseHypothesis],
    inliers: Sequence[EntryInliers],
    intrinsics: CameraIntrinsics,
    pnp: PnpConfig,
    config: JointConfig,
) -> PoseHypothesis | None:
    """The joint pose of the largest consistent group of hypotheses, refined from the
    member pose under which the union keeps the most inliers, as a hypothesis, with its
    covariance from the union's inliers."""
    if len(hypotheses) < config.min_entries:
        return None
    group = consistent_group(
        np.array([h.pose_world for h in hypotheses]),
        np.array([h.n_inliers for h in hypotheses]),
        config,
    )
    if len(group) < config.min_entries:
        return None
    # LM keeps its start's basin: start from the member pose the union agrees with most
    # (the anchor, whose entry the hypothesis names, stays the group's)
    anchor = hypotheses[group[0]]
    members = [inliers[g] for g in group]
    starts = [hypotheses[g].T_world_from_cam for g in group]
    joint = joint_pose_from_best_start(members, starts, intrinsics, pnp, config)
    if joint is None:
        return None
    members = [hypotheses[group[m]] for m in joint.members]
    return PoseHypothesis(
        entry_id=anchor.entry_id,
        T_world_from_cam=joint.T_world_from_cam,
        pose_world=planar_from_T_world_from_cam(joint.T_world_from_cam),
        entry_pose_world=anchor.entry_pose_world,
        e_vlad=anchor.e_vlad,
        n_matches=joint.n_correspondences,
        n_inliers=joint.n_inliers,
        reprojection_error_px=joint.reprojection_error_px,
        joint=True,
        entry_ids=tuple(h.entry_id for h in members),
        method="joint",
        entry_tags=anchor.entry_tags,
        covariance_px1=planar_pose_covariance(
            joint.T_world_from_cam,
            joint.inlier_points_world,
            intrinsics,
            keypoint_scales=joint.inlier_scales,
        ),
    )


def pooled_hypothesis(
    keypoints_px: np.ndarray,
    refs: Sequence[ReferenceEntry],
    matches: Sequence[np.ndarray],
    e_vlad: dict[int, float],
    intrinsics: CameraIntrinsics,
    config: PoseConfig,
    rng: np.random.Generator,
    scales: np.ndarray | None,
    descriptors: np.ndarray | None,
) -> PoseHypothesis | None:
    """The pooled pose of the frame's entries (``config.pooled``), refit on every entry's
    points matched by projection from it when ``config.refine`` is set."""
    pooled = _pooled(keypoints_px, refs, matches, e_vlad, intrinsics, config, rng, scales)
    if pooled is None or config.refine is None:
        return pooled
    assert descriptors is not None  # checked by pose_hypotheses
    return _refined_pooled(
        pooled, keypoints_px, descriptors, refs, e_vlad, intrinsics, config, rng, scales
    )


def alternative_hypothesis(
    hypotheses: Sequence[PoseHypothesis],
    keypoints_px: np.ndarray,
    refs: Sequence[ReferenceEntry],
    matches: Sequence[np.ndarray],
    e_vlad: dict[int, float],
    intrinsics: CameraIntrinsics,
    config: PoseConfig,
    rng: np.random.Generator,
    scales: np.ndarray | None,
) -> PoseHypothesis | None:
    """A second pose for a poorly pinned frame (``AlternativeConfig``): the pooled pose of
    the matches that the most-inlier hypothesis leaves unexplained, method
    "alternative"; None for an ordinary frame or when it lies too near that pose."""
    alternative = config.alternative
    assert alternative is not None and config.pooled is not None
    if not _poorly_pinned(hypotheses, alternative.min_spread_m):
        return None
    consensus = max(hypotheses, key=lambda h: h.n_inliers)
    T_query_from_world = invert_rigid(consensus.T_world_from_cam)
    unexplained = [
        pairs[
            ~within_threshold(
                keypoints_px[pairs[:, 0]],
                ref.points_cam[pairs[:, 1]],
                T_query_from_world @ ref.T_world_from_cam,
                intrinsics,
                alternative.residual_px,
            )
        ]
        for ref, pairs in zip(refs, matches, strict=True)
    ]
    found = _pooled(keypoints_px, refs, unexplained, e_vlad, intrinsics, config, rng, scales)
    if found is None or (
        np.linalg.norm(found.pose_world[:2] - consensus.pose_world[:2]) < alternative.min_offset_m
    ):
        return None
    return replace(found, method="alternative")


def _poorly_pinned(hypotheses: Sequence[PoseHypothesis], min_spread_m: float) -> bool:
    """Whether the median position spread (1 px) of the per-entry hypotheses' pose
    covariances exceeds ``min_spread_m`` (at least two with one)."""
    spreads = [position_spread_m(h.covariance_px1) for h in hypotheses if not h.joint]
    spreads = [v for v in spreads if np.isfinite(v)]
    return len(spreads) >= 2 and float(np.median(spreads)) > min_spread_m


def _pooled(
    keypoints_px: np.ndarray,
    refs: Sequence[ReferenceEntry],
    matches: Sequence[np.ndarray],
    e_vlad: dict[int, float],
    intrinsics: CameraIntrinsics,
    config: PoseConfig,
    rng: np.random.Generator,
    keypoint_scales: np.ndarray | None,
    guesses_T_world_from_cam: Sequence[np.ndarray] = (),
    fallback: bool = True,
) -> PoseHypothesis | None:
    """The pooled pose of the frame's entries as a hypothesis: not marked ``joint`` (it
    stands in for the per-entry hypotheses the frame did not get, and the paper's
    measurement model leaves joint ones out); entry, entry pose and e_vlad are those of
    the member with the most matches; its covariance from the pooled inliers."""
    assert config.pooled is not None
    pose = estimate_pooled_pose(
        keypoints_px,
        [r.T_world_from_cam for r in refs],
        [r.points_cam for r in refs],
        matches,
        intrinsics,
        config.pnp,
        rng,
        config.pooled,
        keypoint_scales,
        guesses_T_world_from_cam,
        fallback,
    )
    if pose is None:
        return None
    anchor = refs[max(pose.members, key=lambda m: len(matches[m]))]
    return PoseHypothesis(
        entry_id=anchor.entry_id,
        T_world_from_cam=pose.T_world_from_cam,
        pose_world=planar_from_T_world_from_cam(pose.T_world_from_cam),
        entry_pose_world=anchor.pose_world,
        e_vlad=float(e_vlad[anchor.entry_id]),
        n_matches=pose.n_correspondences,
        n_inliers=pose.n_inliers,
        reprojection_error_px=pose.reprojection_error_px,
        entry_ids=tuple(refs[m].entry_id for m in pose.members),
        method="pooled",
        entry_tags=anchor.tags,
        covariance_px1=planar_pose_covariance(
            pose.T_world_from_cam,
            pose.inlier_points_world,
            intrinsics,
            keypoint_scales=pose.inlier_scales,
        ),
    )


def _refined_pooled(
    pooled: PoseHypothesis,
    keypoints_px: np.ndarray,
    descriptors: np.ndarray,
    refs: Sequence[ReferenceEntry],
    e_vlad: dict[int, float],
    intrinsics: CameraIntrinsics,
    config: PoseConfig,
    rng: np.random.Generator,
    scales: np.ndarray | None,
) -> PoseHypothesis:
    """The pooled pose refit on every entry's points matched by projection from it (as
    each entry's own pose is): the pooled pose chooses the consensus set of those matches
    and is refit on it, with pooled PnP's rules; kept when it keeps more inliers, else
    the pooled pose as it was. No RANSAC on these matches: they were chosen around the
    pooled pose."""
    window = config.refine
    assert window is not None
    grid = KeypointGrid(keypoints_px, descriptors, intrinsics, window.radius_px)
    T_query_from_world = invert_rigid(pooled.T_world_from_cam)
    matches = [
        match_by_projection(
            grid,
            ref.descriptors,
            ref.points_cam,
            T_query_from_world @ ref.T_world_from_cam,
            window,
        )
        for ref in refs
    ]
    refined = _pooled(
        keypoints_px,
        refs,
        matches,
        e_vlad,
        intrinsics,
        config,
        rng,
        scales,
        [pooled.T_world_from_cam],
        fallback=False,
    )
    if refined is None or refined.n_inliers <= pooled.n_inliers:
        return pooled
    return refined

"""The pose stage of a frame (docs/method.md section 6, steps 3-5): its retrieved entries'
matches -> pose hypotheses T_world_from_query = T_world_from_ref @ T_ref_from_query.

Guided PnP: the entries are visited by decreasing number of matches; the first gets a
full RANSAC (none when the retrieval prior carries a heading: the prior's pose, at the
entry's height and tilt, is the first guess), every other entry is scored against the
poses found so far and refit on its own inliers (``pnp.estimate_relative_pose_guided``).
An entry those poses do not explain gets its own RANSAC only while the pose is
unconfirmed (``PoseConfig.fallback_until_confirmed``); such entries wait until every
entry has been tried, so a confirmation from any of them spares the others' RANSAC.
Every per-entry hypothesis comes from that entry's own correspondences. Each accepted
pose is then refit on the entry's points matched by projection from it
(``vision.projection``), kept when it keeps more inliers, and carries the covariance of
its planar pose from its inliers (``vision.pose_covariance``). Then the poses of several
entries (``localize.combined``): the joint pose, the pooled pose of a frame without any
per-entry pose, and the alternative pose of a poorly pinned frame.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import invert_rigid, planar_from_T_world_from_cam, wrap_angle
from monoloc.core.prior import RetrievalPrior
from monoloc.server.localize.combined import (
    alternative_hypothesis,
    joint_hypothesis,
    pooled_hypothesis,
)
from monoloc.server.localize.config import PoseConfig
from monoloc.server.localize.results import PoseHypothesis, ReferenceEntry
from monoloc.server.vision.joint import EntryInliers, JointConfig
from monoloc.server.vision.pnp import (
    RelativePose,
    estimate_relative_pose,
    estimate_relative_pose_guided,
)
from monoloc.server.vision.pose_covariance import planar_pose_covariance
from monoloc.server.vision.projection import KeypointGrid, refine_by_projection


def pose_hypotheses(
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
    """PnP against each reference (its (K, 2) query/reference index pairs into
    ``keypoints_px`` (N, 2) and its points), then the poses of several entries (appended
    last). ``keypoint_scales`` (N,): the keypoints' pyramid scales (``Features.scales``;
    None: all at full resolution), which weigh each inlier in the pose covariance.
    ``descriptors`` (N, 32) uint8: the keypoints' descriptors, for the refit by projection
    (``config.refine``; InvalidInputError without them). Returns the hypotheses in the
    references' order and (entry id, reason) of the rejected references."""
    keypoints_px, scales = checked_pose_inputs(keypoints_px, keypoint_scales, descriptors, config)
    solved = _solve_entries(keypoints_px, refs, matches, intrinsics, config, rng, prior)
    pairs_used = matches
    if config.refine is not None:
        pairs_used, solved = _refined_by_projection(
            keypoints_px, descriptors, refs, matches, solved, intrinsics, config
        )
    return hypotheses_from_solved(
        keypoints_px,
        refs,
        matches,
        pairs_used,
        solved,
        e_vlad,
        intrinsics,
        config,
        rng,
        scales,
        descriptors,
    )


def checked_pose_inputs(
    keypoints_px: np.ndarray,
    keypoint_scales: np.ndarray | None,
    descriptors: np.ndarray | None,
    config: PoseConfig,
) -> tuple[np.ndarray, np.ndarray | None]:
    """The pose stage's query arrays as float64, once a frame: keypoints (N, 2) and their
    scales (N,) or None; InvalidInputError for scales of another length, or no
    descriptors when ``config.refine`` needs them."""
    keypoints_px = np.asarray(keypoints_px, dtype=np.float64)
    scales = None if keypoint_scales is None else np.asarray(keypoint_scales, dtype=np.float64)
    if scales is not None and scales.shape != (len(keypoints_px),):
        raise InvalidInputError(
            f"{len(keypoints_px)} keypoints but keypoint scales of shape {scales.shape}"
        )
    if config.refine is not None and descriptors is None:
        raise InvalidInputError("refining by projection needs the query's descriptors")
    return keypoints_px, scales


def hypotheses_from_solved(
    keypoints_px: np.ndarray,
    refs: Sequence[ReferenceEntry],
    matches: Sequence[np.ndarray],
    pairs_used: Sequence[np.ndarray],
    solved: Sequence[RelativePose],
    e_vlad: dict[int, float],
    intrinsics: CameraIntrinsics,
    config: PoseConfig,
    rng: np.random.Generator,
    scales: np.ndarray | None,
    descriptors: np.ndarray | None,
) -> tuple[list[PoseHypothesis], list[tuple[int, str]]]:
    """The hypotheses of the entries' solved poses (``pairs_used``: each entry's pairs the
    pose was solved on), in the references' order, then the poses of several entries
    (joint, pooled, alternative, as ``config`` asks), and (entry id, reason) of the
    rejected references."""
    hypotheses: list[PoseHypothesis] = []
    rejected: list[tuple[int, str]] = []
    inliers: list[EntryInliers] = []
    for ref, pairs, rel in zip(refs, pairs_used, solved, strict=True):
        if not rel.accepted:
            rejected.append((ref.entry_id, rel.reject_reason or "rejected"))
            continue
        kept = pairs[rel.inlier_mask]
        hypotheses.append(entry_hypothesis(ref, rel, kept, len(pairs), e_vlad, intrinsics, scales))
        inliers.append(
            EntryInliers(
                ref.T_world_from_cam,
                keypoints_px[kept[:, 0]],
                ref.points_cam[kept[:, 1]],
                None if scales is None else scales[kept[:, 0]],
            )
        )
    if config.joint is not None:
        joint = joint_hypothesis(hypotheses, inliers, intrinsics, config.pnp, config.joint)
        if joint is not None:
            hypotheses.append(joint)
    if config.pooled is not None and not hypotheses and refs:
        pooled = pooled_hypothesis(
            keypoints_px, refs, matches, e_vlad, intrinsics, config, rng, scales, descriptors
        )
        if pooled is not None:
            hypotheses.append(pooled)
    if config.alternative is not None:
        found = alternative_hypothesis(
            hypotheses, keypoints_px, refs, matches, e_vlad, intrinsics, config, rng, scales
        )
        if found is not None:
            hypotheses.append(found)
    return hypotheses, rejected


def entry_hypothesis(
    ref: ReferenceEntry,
    rel: RelativePose,
    kept: np.ndarray,
    n_matches: int,
    e_vlad: dict[int, float],
    intrinsics: CameraIntrinsics,
    scales: np.ndarray | None,
) -> PoseHypothesis:
    """The hypothesis of one accepted entry pose, from its inlier pairs ``kept`` (M, 2)
    (query keypoint, entry point), with the covariance of its planar pose at 1 px."""
    # compose_hypothesis without its rigidity checks: entry poses are checked when stored
    # (storage.entry_checks) and an accepted pose is finite and rigid by construction.
    T_world_from_ref = np.asarray(ref.T_world_from_cam, dtype=np.float64)
    T_world_from_query = T_world_from_ref @ rel.T_ref_from_query
    points_world = ref.points_cam[kept[:, 1]] @ T_world_from_ref[:3, :3].T
    covariance = planar_pose_covariance(
        T_world_from_query,
        points_world + T_world_from_ref[:3, 3],
        intrinsics,
        keypoint_scales=None if scales is None else scales[kept[:, 0]],
    )
    return PoseHypothesis(
        entry_id=ref.entry_id,
        T_world_from_cam=T_world_from_query,
        pose_world=planar_from_T_world_from_cam(T_world_from_query),
        entry_pose_world=ref.pose_world,
        e_vlad=float(e_vlad[ref.entry_id]),
        n_matches=n_matches,
        n_inliers=rel.n_inliers,
        reprojection_error_px=rel.reprojection_error_px,
        method=rel.method,
        covariance_px1=covariance,
        entry_tags=ref.tags,
    )


def _solve_entries(
    keypoints_px: np.ndarray,
    refs: Sequence[ReferenceEntry],
    matches: Sequence[np.ndarray],
    intrinsics: CameraIntrinsics,
    config: PoseConfig,
    rng: np.random.Generator,
    prior: RetrievalPrior | None,
) -> list[RelativePose]:
    """One RelativePose per reference, in the references' order.

    By decreasing number of matches, each entry seeded by the poses (T_world_from_query)
    found so far (the first, with nothing found yet, gets its own RANSAC). An entry those
    poses do not explain waits; if, once every entry has been tried, the pose is still not
    confirmed, the waiting entries are tried again in the same order with the poses found
    by then, each falling back to its own RANSAC while the pose is still unconfirmed.
    """
    solved: list[RelativePose | None] = [None] * len(refs)
    order = sorted(range(len(refs)), key=lambda j: -len(matches[j]))
    # The poses found so far (T_world_from_query), the prior's guess first if any.
    found_world = np.empty((len(refs) + 1, 4, 4))
    n_found = 0
    votes = _Confirmation(config.fallback_until_confirmed, config.joint or JointConfig())
    if prior is not None and prior.yaw_rad is not None and refs:
        found_world[0] = _prior_guess(prior, refs[order[0]].T_world_from_cam)
        n_found = 1
        # The filter's prediction is one vote: made without this frame, it confirms the
        # pose once an entry's own correspondences agree with it.
        votes.add(found_world[0])

    def solve(j: int, fallback: bool) -> RelativePose:
        nonlocal n_found
        ref, pairs = refs[j], matches[j]
        pixels, points = keypoints_px[pairs[:, 0]], ref.points_cam[pairs[:, 1]]
        if n_found:
            # every found pose brought into this entry's frame: T_ref_from_world @ T
            guesses = invert_rigid(ref.T_world_from_cam) @ found_world[:n_found]
            rel = estimate_relative_pose_guided(
                pixels, points, guesses, intrinsics, config.pnp, rng, fallback
            )
        else:
            rel = estimate_relative_pose(pixels, points, intrinsics, config.pnp, rng)
        if rel.accepted:
            found_world[n_found] = ref.T_world_from_cam @ rel.T_ref_from_query
            votes.add(found_world[n_found])
            n_found += 1
        solved[j] = rel
        return rel

    waiting = []
    for j in order:
        rel = solve(j, fallback=False)
        if not rel.accepted and rel.method == "guided":  # not explained, no RANSAC yet
            waiting.append(j)
    if not votes.confirmed:
        for j in waiting:  # with the poses found by then; own RANSAC while unconfirmed
            solve(j, fallback=not votes.confirmed)
    return [rel for rel in solved if rel is not None]


class _Confirmation:
    """Whether ``needed`` accepted poses agree on one pose (within the joint gates)."""

    def __init__(self, needed: int, gates: JointConfig) -> None:
        self.needed = needed
        self.gates = gates
        self.poses_world: list[np.ndarray] = []
        self.confirmed = False

    def add(self, T_world_from_query: np.ndarray) -> None:
        if self.confirmed:
            return
        self.poses_world.append(planar_from_T_world_from_cam(T_world_from_query))
        poses = np.array(self.poses_world)
        agree = (np.hypot(*(poses[:, :2] - poses[-1, :2]).T) <= self.gates.position_gate_m) & (
            np.abs(wrap_angle(poses[:, 2] - poses[-1, 2])) <= self.gates.yaw_gate_rad
        )
        self.confirmed = int(agree.sum()) >= self.needed


def _prior_guess(prior: RetrievalPrior, T_world_from_ref: np.ndarray) -> np.ndarray:
    """A query pose (4, 4) T_world_from_cam from a planar prior with a heading: the
    reference camera turned about the vertical to the prior's heading and moved to its
    position, keeping the reference's height, pitch and roll."""
    ref = planar_from_T_world_from_cam(T_world_from_ref)
    turn = float(prior.yaw_rad) - ref[2]
    c, s = np.cos(turn), np.sin(turn)
    T = np.array(T_world_from_ref, dtype=np.float64)
    T[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ T[:3, :3]
    T[0, 3], T[1, 3] = prior.x_m, prior.y_m
    return T


def _refined_by_projection(
    keypoints_px: np.ndarray,
    descriptors: np.ndarray,
    refs: Sequence[ReferenceEntry],
    matches: Sequence[np.ndarray],
    solved: Sequence[RelativePose],
    intrinsics: CameraIntrinsics,
    config: PoseConfig,
) -> tuple[list[np.ndarray], list[RelativePose]]:
    """Each accepted entry's pose refit on the entry's points matched by projection from
    that pose (the query keypoints near where the pose puts each point compete, instead
    of the whole image), kept when it keeps more inliers. Returns the entries' (K, 2)
    pairs and poses, the refined ones replaced."""
    window = config.refine
    assert window is not None
    pairs_out, solved_out = list(matches), list(solved)
    grid = None
    for j, (ref, rel) in enumerate(zip(refs, solved, strict=True)):
        if not rel.accepted:
            continue
        if grid is None:
            grid = KeypointGrid(keypoints_px, descriptors, intrinsics, window.radius_px)
        refined = refine_by_projection(
            grid, ref.descriptors, ref.points_cam, rel, config.pnp, window
        )
        if refined is not None:
            pairs_out[j], solved_out[j] = refined
    return pairs_out, solved_out

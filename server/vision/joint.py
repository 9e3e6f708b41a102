"""One pose from every consistent retrieved entry: the joint (multi-entry) PnP pose.

The k retrieved entries are neighbours seeing one place. Each gives a hypothesis from its
own correspondences (docs/method.md 6.5); together their inliers constrain the query far
better than any one of them (hloc's multi-image PnP over covisible references does the
same). Here:

1. the *consistent* entries are the largest group (by total inliers) of accepted
   hypotheses within ``position_gate_m`` / ``yaw_gate_rad`` of one of them (the anchor);
2. each member's inlier 3D points are brought into the world frame (T_world_from_ref);
3. the union is scored against the anchor's pose and refined by Levenberg-Marquardt
   (``pnp.refine_from_pose``: inlier selection, LM, re-selection), only a member's own
   inliers being candidates. LM keeps the basin it starts in, so the anchor is the
   member whose own pose the union agrees with most (:func:`best_start`), not the first
   of a tie: distant facades leave a lateral / yaw ambiguity (0.45 m and 1.2 deg on a
   held-out city) whose two poses are both within the gates and both fit their own
   entry's inliers.

World coordinates can be kilometres: the union is expressed in a frame translated to the
anchor's camera position (a pure translation of the world frame) so LM works on numbers
of the scene's size. Pure: arrays in, a pose out.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import invert_rigid, wrap_angle
from monoloc.server.vision.pnp import (
    RANSAC_METHODS,
    PnpConfig,
    RelativePose,
    estimate_relative_pose,
    estimate_relative_pose_guided,
    refine_from_pose,
    robust_refit,
)


@dataclass(frozen=True)
class JointConfig:
    """Joint-pose settings. position_gate_m / yaw_gate_rad: a hypothesis within these of
    the anchor's (planar) joins the union; min_entries: fewer consistent entries give no
    joint pose (one entry's pose is already its own hypothesis); rounds: inlier selection
    + LM rounds on the union (the PnP config's threshold and LM budget).
    cauchy_scale_sigmas / cauchy_rounds: the union's pose is then refit under a Cauchy
    loss whose scale is that many robust standard deviations of the inliers' errors
    (each error divided by its keypoint's pyramid scale), in that many reweighted LM
    rounds (``pnp.robust_refit``): the union's inliers carry a tail of errors of one to
    three pixels that least squares follows (the joint pose's median error on error-free
    cities fell by 15-20 %); 2.385 sigmas keep 95 % of least squares' efficiency on
    Gaussian errors. cauchy_rounds 0 stops at least squares (a bench baseline)."""

    position_gate_m: float = 0.5
    yaw_gate_rad: float = math.radians(2.0)
    min_entries: int = 2
    rounds: int = 2
    cauchy_scale_sigmas: float = 2.385
    cauchy_rounds: int = 2

    def __post_init__(self) -> None:
        if not (self.position_gate_m > 0 and self.yaw_gate_rad > 0):
            raise InvalidInputError(f"JointConfig gates must be positive: {self}")
        if self.min_entries < 2 or self.rounds < 1:
            raise InvalidInputError(f"JointConfig needs min_entries >= 2, rounds >= 1: {self}")
        if not (self.cauchy_scale_sigmas > 0 and self.cauchy_rounds >= 0):
            raise InvalidInputError(
                f"JointConfig needs cauchy_scale_sigmas > 0 and cauchy_rounds >= 0: {self}"
            )


@dataclass(frozen=True)
class EntryInliers:
    """One entry's share of the union: its pose (4, 4) T_world_from_ref, its inlier query
    pixels (M, 2) and their 3D points (M, 3) in the reference camera frame, and the query
    keypoints' pyramid scales (M,) (None: all at full resolution; see ``PnpConfig``)."""

    T_world_from_ref: np.ndarray
    pixels_px: np.ndarray
    points_ref: np.ndarray
    keypoint_scales: np.ndarray | None = None


@dataclass(frozen=True)
class JointPose:
    """The joint pose: T_world_from_cam (4, 4) of the query, the members it used (indices
    into the hypotheses given), inliers of the union and their mean reprojection error;
    the inliers' 3D points (n_inliers, 3) in the world frame and their query keypoints'
    pyramid scales (n_inliers,) (None when none were given), for the pose's covariance
    (``vision.pose_covariance``)."""

    T_world_from_cam: np.ndarray
    members: tuple[int, ...]
    n_correspondences: int
    n_inliers: int
    reprojection_error_px: float
    inlier_points_world: np.ndarray
    inlier_scales: np.ndarray | None = None


def consistent_group(
    poses_world: np.ndarray, weights: np.ndarray, config: JointConfig
) -> list[int]:
    """Indices of the largest group of planar poses (H, 3) that agree with one of them
    (the anchor, first in the list), the group's size being the sum of ``weights`` (H,)
    (inlier counts). Ties go to the earlier anchor."""
    poses = np.asarray(poses_world, dtype=np.float64).reshape(-1, 3)
    if len(poses) == 0:
        return []
    dist = np.hypot(poses[:, None, 0] - poses[None, :, 0], poses[:, None, 1] - poses[None, :, 1])
    dyaw = np.abs(wrap_angle(poses[:, None, 2] - poses[None, :, 2]))
    agree = (dist <= config.position_gate_m) & (dyaw <= config.yaw_gate_rad)
    anchor = int(np.argmax(agree @ np.asarray(weights, dtype=np.float64)))
    others = [j for j in np.flatnonzero(agree[anchor]).tolist() if j != anchor]
    return [anchor, *others]


def _union_local(entries: Sequence[EntryInliers], origin_world: np.ndarray):
    """The entries' inlier points in the world frame translated to ``origin_world`` (M, 3),
    their pixels (M, 2), scales (M,) and the entries' bounds in the union."""
    points, pixels, scales = [], [], []
    for e in entries:
        T = np.asarray(e.T_world_from_ref, dtype=np.float64)
        p_ref = np.asarray(e.points_ref, dtype=np.float64).reshape(-1, 3)
        points.append(p_ref @ T[:3, :3].T + (T[:3, 3] - origin_world))
        pixels.append(np.asarray(e.pixels_px, dtype=np.float64).reshape(-1, 2))
        scales.append(
            np.ones(len(p_ref))
            if e.keypoint_scales is None
            else np.asarray(e.keypoint_scales, dtype=np.float64).reshape(-1)
        )
    bounds = np.cumsum([0] + [len(p) for p in points]).tolist()
    return np.concatenate(points), np.concatenate(pixels), np.concatenate(scales), bounds


def best_start(
    entries: Sequence[EntryInliers],
    starts_T_world_from_cam: Sequence[np.ndarray],
    intrinsics: CameraIntrinsics,
    pnp: PnpConfig,
) -> int:
    """Index of the pose (4, 4 each) under which the most of the union's correspondences
    reproject within ``pnp.reprojection_error_px`` (ties: the first)."""
    starts = [np.asarray(T, dtype=np.float64) for T in starts_T_world_from_cam]
    if len(starts) <= 1:
        return 0
    origin_world = starts[0][:3, 3].copy()
    points_local, pixels, _, _ = _union_local(entries, origin_world)
    return _best_start(points_local, pixels, origin_world, starts, intrinsics, pnp)


def _best_start(points_local, pixels, origin_world, starts, intrinsics, pnp) -> int:
    """:func:`best_start` on the union (points (M, 3) translated to ``origin_world``)."""
    from monoloc.server.vision._pnp_kernel import count_inliers

    R = np.empty((len(starts), 3, 3))
    t = np.empty((len(starts), 3))
    for g, T in enumerate(starts):
        T_local_from_cam = T.copy()
        T_local_from_cam[:3, 3] -= origin_world
        T_cam_from_local = invert_rigid(T_local_from_cam)
        R[g], t[g] = T_cam_from_local[:3, :3], T_cam_from_local[:3, 3]
    counts = np.zeros(len(starts), dtype=np.int64)
    K = intrinsics.K
    count_inliers(
        np.ascontiguousarray(points_local), np.ascontiguousarray(pixels), R, t,
        K[0, 0], K[1, 1], K[0, 2], K[1, 2], pnp.reprojection_error_px, counts,
    )  # fmt: skip
    return int(np.argmax(counts))


def estimate_joint_pose(
    entries: Sequence[EntryInliers],
    T_world_from_cam_init: np.ndarray,
    intrinsics: CameraIntrinsics,
    pnp: PnpConfig,
    config: JointConfig,
) -> JointPose | None:
    """Refine ``T_world_from_cam_init`` (4, 4) on the union of the entries' inliers in the
    world frame. None when fewer than ``config.min_entries`` entries keep inliers, the
    union keeps fewer than ``pnp.min_inliers``, or LM fails."""
    if len(entries) < config.min_entries:
        return None
    init = np.asarray(T_world_from_cam_init, dtype=np.float64)
    origin_world = init[:3, 3].copy()
    union = _union_local(entries, origin_world)
    return _joint_pose(union, origin_world, init, entries, intrinsics, pnp, config)


def joint_pose_from_best_start(
    entries: Sequence[EntryInliers],
    starts_T_world_from_cam: Sequence[np.ndarray],
    intrinsics: CameraIntrinsics,
    pnp: PnpConfig,
    config: JointConfig,
) -> JointPose | None:
    """:func:`estimate_joint_pose` from the :func:`best_start` of ``starts`` (4, 4 each),
    the union built once for both (it was built twice, a quarter of the joint pose's
    time)."""
    if len(entries) < config.min_entries:
        return None
    starts = [np.asarray(T, dtype=np.float64) for T in starts_T_world_from_cam]
    origin_world = starts[0][:3, 3].copy()
    points_local, pixels, scales, bounds = _union_local(entries, origin_world)
    start = 0
    if len(starts) > 1:
        start = _best_start(points_local, pixels, origin_world, starts, intrinsics, pnp)
    if start:  # LM works about its start: the union translated to that camera
        shifted = starts[start][:3, 3].copy()
        points_local = points_local - (shifted - origin_world)
        origin_world = shifted
    union = (points_local, pixels, scales, bounds)
    return _joint_pose(union, origin_world, starts[start], entries, intrinsics, pnp, config)


def _joint_pose(union, origin_world, init, entries, intrinsics, pnp, config) -> JointPose | None:
    """The joint pose refined from ``init`` (4, 4) on ``union`` (``_union_local``'s points
    translated to ``origin_world``, pixels, scales, bounds)."""
    points_local, pixels_all, scales_all, bounds = union
    T_local_from_cam = init.copy()
    T_local_from_cam[:3, 3] -= origin_world
    T_cam_from_local = invert_rigid(T_local_from_cam)
    R, t, mask, errors_px = refine_from_pose(
        points_local,
        pixels_all,
        T_cam_from_local[:3, :3].copy(),
        T_cam_from_local[:3, 3].copy(),
        intrinsics.K,
        pnp,
        config.rounds,
    )
    if R is None or np.count_nonzero(mask) < pnp.min_inliers:
        return None
    if config.cauchy_rounds:
        R, t, errors_px = robust_refit(
            points_local, pixels_all, mask, R, t, intrinsics.K, pnp, scales_all,
            config.cauchy_scale_sigmas, config.cauchy_rounds,
        )  # fmt: skip
        if R is None:
            return None
    members = tuple(j for j in range(len(entries)) if mask[bounds[j] : bounds[j + 1]].any())
    if len(members) < config.min_entries:
        return None
    T_cam_from_local = np.eye(4)
    T_cam_from_local[:3, :3], T_cam_from_local[:3, 3] = R, t
    T_world_from_cam = invert_rigid(T_cam_from_local)
    T_world_from_cam[:3, 3] += origin_world
    n_inliers = int(np.count_nonzero(mask))
    scaled = any(e.keypoint_scales is not None for e in entries)
    return JointPose(
        T_world_from_cam=T_world_from_cam,
        members=members,
        n_correspondences=len(points_local),
        n_inliers=n_inliers,
        reprojection_error_px=float(errors_px[mask].sum()) / n_inliers,
        inlier_points_world=points_local[mask] + origin_world,
        inlier_scales=scales_all[mask] if scaled else None,
    )


@dataclass(frozen=True)
class PooledConfig:
    """Pooled-PnP settings (:func:`estimate_pooled_pose`). min_entries: entries that must
    each keep at least ``min_inliers_per_entry`` of the pose's inliers (a pose that one
    entry's matches explain alone is that entry's to give); iterations: the RANSAC budget
    on the pooled matches (their inlier ratio is lower than one right entry's, since the
    wrong entries' matches are pooled too); neighbour_radius_m: only entries within this
    (planar) distance of the entry with the most matches are pooled: entries that see one
    place are neighbours, and a frame whose retrieved entries are scattered over the map
    (a night frame against a day map) then does not pay a long RANSAC on matches that
    cannot agree (about 20 ms a frame at 1000 iterations).

    ransac: the RANSAC on the pooled matches (``PnpConfig.ransac``): "usac", OpenCV's USAC
    (MSAC score, adaptive stop), by default. On bench/localize.py's 16 pooled frames it
    found the same inliers as the classic RANSAC (within one) in 3-7 ms instead of
    10-27 ms: the classic one's budget for a 15-20 % inlier ratio is its full 1000
    iterations."""

    min_entries: int = 2
    min_inliers_per_entry: int = 4
    iterations: int = 1000
    neighbour_radius_m: float = 25.0
    ransac: str = "usac"

    def __post_init__(self) -> None:
        if self.min_entries < 2 or self.min_inliers_per_entry < 1 or self.iterations < 1:
            raise InvalidInputError(f"invalid PooledConfig {self}")
        if self.ransac not in RANSAC_METHODS:
            raise InvalidInputError(f"PooledConfig.ransac must be one of {RANSAC_METHODS}: {self}")
        if not self.neighbour_radius_m > 0:
            raise InvalidInputError(f"PooledConfig.neighbour_radius_m must be > 0: {self}")


def estimate_pooled_pose(
    keypoints_px: np.ndarray,
    T_world_from_refs: Sequence[np.ndarray],
    points_refs: Sequence[np.ndarray],
    matches: Sequence[np.ndarray],
    intrinsics: CameraIntrinsics,
    pnp: PnpConfig,
    rng: np.random.Generator,
    config: PooledConfig,
    keypoint_scales: np.ndarray | None = None,
    guesses_T_world_from_cam: Sequence[np.ndarray] = (),
    fallback: bool = True,
) -> JointPose | None:
    """One PnP RANSAC on the matches of every retrieved entry together, for a frame whose
    entries each had too few matches or inliers for a pose of their own (hloc pools a
    query's 2D-3D matches over its retrieved images the same way).

    keypoints_px (N, 2): the query's keypoints; per entry j: T_world_from_refs[j] (4, 4),
    points_refs[j] (M_j, 3) its 3D points in its camera frame, matches[j] (K_j, 2) (query
    keypoint, entry point) index pairs. The points are expressed in the frame of the entry
    with the most matches (the anchor: PnP's rotation check is relative to it), the entries
    farther than ``config.neighbour_radius_m`` from it left out; a query
    keypoint matched in several entries keeps its match in the entry with more matches.
    ``keypoint_scales`` (N,): the keypoints' pyramid scales (None: all at full resolution).
    ``guesses_T_world_from_cam``: poses (4, 4) of the query found elsewhere (the pooled
    pose itself, when it is refit on matches by projection): as in guided PnP the one
    that keeps the most pooled matches chooses the consensus set, refit on it, and the
    pose stands if it keeps ``pnp.min_inliers`` and the members below; otherwise (or
    without guesses) the RANSAC on the pooled matches runs as before. The RANSAC pays its
    full budget on pooled matches (their inlier ratio is low: 15-20 % on bench/localize.py's
    frames, about 20 ms), a guess one scoring pass and a refit.
    With ``fallback`` False there is no RANSAC: only the guesses are tried.
    ``members`` indexes the entries keeping inliers. None when RANSAC finds no pose with
    ``pnp.min_inliers`` inliers, or fewer than ``config.min_entries`` entries keep
    ``config.min_inliers_per_entry`` of them."""
    order = sorted(range(len(matches)), key=lambda j: -len(matches[j]))
    order = [j for j in order if len(matches[j])]
    if not order:
        return None
    anchor = order[0]
    centre = np.asarray(T_world_from_refs[anchor], dtype=np.float64)[:2, 3]
    order = [
        j
        for j in order
        if np.hypot(*(np.asarray(T_world_from_refs[j], dtype=np.float64)[:2, 3] - centre))
        <= config.neighbour_radius_m
    ]
    if len(order) < config.min_entries:
        return None
    T_anchor_from_world = invert_rigid(np.asarray(T_world_from_refs[anchor], dtype=np.float64))
    keypoints = np.asarray(keypoints_px, dtype=np.float64)
    pixels, points, owners, pair_scales, seen = [], [], [], [], set()
    for j in order:
        pairs = np.asarray(matches[j]).reshape(-1, 2)
        fresh = np.array([int(q) not in seen for q in pairs[:, 0]], dtype=bool)
        pairs = pairs[fresh]
        if not len(pairs):
            continue
        seen.update(int(q) for q in pairs[:, 0])
        T = T_anchor_from_world @ np.asarray(T_world_from_refs[j], dtype=np.float64)
        p_ref = np.asarray(points_refs[j], dtype=np.float64)[pairs[:, 1]]
        points.append(p_ref @ T[:3, :3].T + T[:3, 3])
        pixels.append(keypoints[pairs[:, 0]])
        owners.append(np.full(len(pairs), j))
        if keypoint_scales is not None:
            pair_scales.append(np.asarray(keypoint_scales, dtype=np.float64)[pairs[:, 0]])
    pooled = dataclasses.replace(
        pnp, iterations=max(pnp.iterations, config.iterations), ransac=config.ransac
    )
    pixels_all, points_all = np.concatenate(pixels), np.concatenate(points)
    scales_all = np.concatenate(pair_scales) if keypoint_scales is not None else None
    owners_all = np.concatenate(owners)
    rel, members = None, ()
    if len(guesses_T_world_from_cam):
        guesses = T_anchor_from_world @ np.asarray(guesses_T_world_from_cam, dtype=np.float64)
        # the guess only has to keep min_inliers (a pooled set's inlier ratio is low)
        guided = dataclasses.replace(pooled, guided_min_inlier_ratio=0.0)
        rel = estimate_relative_pose_guided(
            pixels_all, points_all, guesses, intrinsics, guided, rng, False
        )
        members = _pooled_members(rel, owners_all, config)
    if len(members) < config.min_entries and fallback:
        rel = estimate_relative_pose(pixels_all, points_all, intrinsics, pooled, rng)
        members = _pooled_members(rel, owners_all, config)
    if len(members) < config.min_entries:
        return None
    T_world_from_anchor = np.asarray(T_world_from_refs[anchor], dtype=np.float64)
    kept = rel.inlier_mask
    return JointPose(
        T_world_from_cam=T_world_from_anchor @ rel.T_ref_from_query,
        members=members,
        n_correspondences=int(sum(len(p) for p in pixels)),
        n_inliers=rel.n_inliers,
        reprojection_error_px=rel.reprojection_error_px,
        inlier_points_world=points_all[kept] @ T_world_from_anchor[:3, :3].T
        + T_world_from_anchor[:3, 3],
        inlier_scales=None if scales_all is None else scales_all[kept],
    )


def _pooled_members(rel: RelativePose, owners: np.ndarray, config: PooledConfig) -> tuple:
    """The entries (indices) keeping ``config.min_inliers_per_entry`` of an accepted
    pooled pose's inliers; () for a rejected pose."""
    if not rel.accepted:
        return ()
    kept, counts = np.unique(owners[rel.inlier_mask], return_counts=True)
    return tuple(
        int(j) for j, n in zip(kept, counts, strict=True) if n >= config.min_inliers_per_entry
    )

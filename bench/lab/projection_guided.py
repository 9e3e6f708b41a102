"""Lab variant (not adopted, 2026-12-02): guided entries matched by projection instead of
globally (issue 52, deliverable 4; docs/notebook/frame_cost.md).

The product matches every retrieved entry against the query's ~1000 descriptors (global
Hamming matching, ~0.34 ms an entry on this 2-core AMD EPYC) before the pose stage. Here
the matches are computed on demand (:class:`EntryMatches`) and the entries are visited in
retrieval order: the first gets its own RANSAC on its global matches, and every later
entry is matched by projection from the poses found so far (one per place) and guided on
those matches (:func:`guided_by_projection`: the guess's inliers among the window's
matches refit with SQPnP + LM, the guided inlier rules). Its global matches are read only
for its own RANSAC, the pooled pose and the alternative pose.

Measured (bench.lab.pose_replay): matching 3.2 -> 0.3 ms of CPU a frame on the held-out
city, the pose stage 0.4-1.2 ms more; but the window finds enough inliers for about one
more entry a frame that global matching rejects (about 20 inliers, a median error twice
the others'), the dusk road's joint pose comes out 0.020 -> 0.025 m (median), and on
bench.accuracy's seed 4721 one more day frame ended beyond 0.25 m. Use:
``FrameStages(match=match_on_demand, poses=projection_guided_pose_hypotheses)``
(``PROJECTION_GUIDED_STAGES``).
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import invert_rigid, planar_from_T_world_from_cam, wrap_angle
from monoloc.core.prior import RetrievalPrior
from monoloc.server.localize.config import PoseConfig
from monoloc.server.localize.frame import FrameStages
from monoloc.server.localize.poses import (
    _Confirmation,
    _prior_guess,
    checked_pose_inputs,
    hypotheses_from_solved,
)
from monoloc.server.localize.results import PoseHypothesis, ReferenceEntry
from monoloc.server.vision.joint import JointConfig
from monoloc.server.vision.matching import MatchConfig, _check, _match_words, _Scratch
from monoloc.server.vision.pnp import (
    PnpConfig,
    RelativePose,
    estimate_relative_pose,
    estimate_relative_pose_guided,
)
from monoloc.server.vision.projection import (
    KeypointGrid,
    ProjectionMatchConfig,
    match_by_projection,
    refine_by_projection,
)


class EntryMatches(Sequence):
    """The matches of one query against several references (as
    :func:`match_against_references` gives them), each reference's computed when first
    read: the pose stage matches an entry by projection when a pose found elsewhere
    predicts where its points appear, and then never reads its global matches.
    ``elapsed_ms``: the time spent matching so far."""

    def __init__(
        self, query_desc: np.ndarray, refs: Sequence[np.ndarray], config: MatchConfig
    ) -> None:
        from monoloc.server.vision._hamming_kernel import match_rows

        self._match_rows = match_rows
        self._query_words = _check(query_desc, "query").view(np.uint64)
        self._refs = [_check(r, f"reference {i}") for i, r in enumerate(refs)]
        self._config = config
        self._found: list[np.ndarray | None] = [None] * len(self._refs)
        self._scratch = None
        self.elapsed_ms = 0.0

    def __len__(self) -> int:
        return len(self._refs)

    def __getitem__(self, j):
        if isinstance(j, slice):
            return [self[i] for i in range(*j.indices(len(self)))]
        found = self._found[j]
        if found is None:
            started = time.perf_counter()
            if self._scratch is None:
                largest = max(len(r) for r in self._refs)
                self._scratch = _Scratch(len(self._query_words), largest)
            found = _match_words(
                self._match_rows, self._query_words, self._refs[j], self._config, self._scratch
            )
            self._found[j] = found
            self.elapsed_ms += (time.perf_counter() - started) * 1e3
        return found


def match_on_demand(
    query_desc: np.ndarray, refs: Sequence[np.ndarray], config: MatchConfig = MatchConfig()
) -> EntryMatches:
    """:func:`match_against_references`, each reference matched when first read
    (:class:`EntryMatches`): the product's matching stage."""
    return EntryMatches(query_desc, refs, config)


def guided_by_projection(
    grid: KeypointGrid,
    ref_descriptors: np.ndarray,
    points_ref_cam: np.ndarray,
    guesses_T_ref_from_query: np.ndarray,
    pnp: PnpConfig,
    config: ProjectionMatchConfig,
    rng: np.random.Generator,
) -> tuple[np.ndarray, RelativePose]:
    """Guided PnP of one entry on its points (M, 3) matched by projection instead of its
    global matches: under each guess (G, 4, 4) T_ref_from_query in turn, the points are
    matched in the window around where the guess projects them, and the guess's inliers
    among those matches are refit as guided PnP's are (``estimate_relative_pose_guided``
    without its RANSAC: SQPnP, LM, the inlier rules on the window's matches). Returns
    (the (K, 2) matches, the pose) of the first guess whose refit is accepted, else of the
    guess that kept the most inliers, its pose rejected (method "guided")."""
    points = np.ascontiguousarray(points_ref_cam, dtype=np.float64).reshape(-1, 3)
    best: tuple[np.ndarray, RelativePose] | None = None
    for T_ref_from_query in np.asarray(guesses_T_ref_from_query, dtype=np.float64):
        pairs = match_by_projection(
            grid, ref_descriptors, points, invert_rigid(T_ref_from_query), config
        )
        rel = estimate_relative_pose_guided(
            grid.keypoints_px[pairs[:, 0]],
            points[pairs[:, 1]],
            T_ref_from_query[None],
            grid.intrinsics,
            pnp,
            rng,
            fallback=False,
        )
        if rel.accepted:
            return pairs, rel
        if best is None or rel.n_inliers > best[1].n_inliers:
            best = (pairs, rel)
    if best is None:
        raise InvalidInputError("guided_by_projection needs at least one guess")
    return best


def projection_guided_pose_hypotheses(
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
    refit_guided: bool = True,
) -> tuple[list[PoseHypothesis], list[tuple[int, str]]]:
    """The product's :func:`pose_hypotheses` with the guided entries matched by projection
    (``_solve_entries`` below); ``matches`` may be an :class:`EntryMatches`.
    ``refit_guided`` False: an entry guided by projection is not matched by projection
    again from its own pose (its matches came from the window already).
    PnP against each reference (its (K, 2) query/reference index pairs into
    ``keypoints_px`` (N, 2) and its points), then the poses of several entries (appended
    last). ``keypoint_scales`` (N,): the keypoints' pyramid scales (``Features.scales``;
    None: all at full resolution), which weigh each inlier in the pose covariance.
    ``descriptors`` (N, 32) uint8: the keypoints' descriptors, for the refit by projection
    (``config.refine``; InvalidInputError without them). Returns the hypotheses in the
    references' order and (entry id, reason) of the rejected references."""
    keypoints_px, scales = checked_pose_inputs(keypoints_px, keypoint_scales, descriptors, config)
    grid = _LazyGrid(keypoints_px, descriptors, intrinsics, config.refine)
    solved, pairs_used = _solve_entries(
        keypoints_px, refs, matches, intrinsics, config, rng, prior, grid
    )
    if config.refine is not None:
        by_projection = refit_guided is False
        pairs_used, solved = _refined_by_projection(
            grid, refs, pairs_used, solved, config, skip_guided=by_projection
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


class _LazyGrid:
    """The query's :class:`KeypointGrid` for the projection window ``window`` (None: no
    matching by projection), built when first needed, once a frame."""

    def __init__(self, keypoints_px, descriptors, intrinsics, window) -> None:
        self.window = window
        self._args = (keypoints_px, descriptors, intrinsics)
        self._grid: KeypointGrid | None = None

    def get(self) -> KeypointGrid:
        if self._grid is None:
            keypoints_px, descriptors, intrinsics = self._args
            self._grid = KeypointGrid(keypoints_px, descriptors, intrinsics, self.window.radius_px)
        return self._grid


_NO_PAIRS = np.zeros((0, 2), dtype=np.int32)


def _solve_entries(
    keypoints_px: np.ndarray,
    refs: Sequence[ReferenceEntry],
    matches: Sequence[np.ndarray],
    intrinsics: CameraIntrinsics,
    config: PoseConfig,
    rng: np.random.Generator,
    prior: RetrievalPrior | None,
    grid: _LazyGrid,
) -> tuple[list[RelativePose], list[np.ndarray]]:
    """One RelativePose per reference, in the references' order, and the (K, 2) pairs
    its inlier mask refers to.

    Each entry is seeded by the poses (T_world_from_query) found so far (the first, with
    nothing found yet, gets its own RANSAC on its global matches). With the projection
    window (``config.refine``) the entries are visited in retrieval order and a seeded
    entry is matched by projection from those poses (``guided_by_projection``): its global
    matches (``matches[j]``, which may compute them on first reading) are read only for
    its own RANSAC. Without it, by decreasing number of global matches, each scored on
    them. An entry those poses do not explain waits; if, once every entry has been tried,
    the pose is still not confirmed, the waiting entries are tried again in the same
    order with the poses found by then, each falling back to its own RANSAC while the
    pose is still unconfirmed.
    """
    n = len(refs)
    solved: list[RelativePose | None] = [None] * n
    pairs_of: list[np.ndarray] = [_NO_PAIRS] * n
    by_projection = grid.window is not None
    order = list(range(n)) if by_projection else sorted(range(n), key=lambda j: -len(matches[j]))
    gates = config.joint or JointConfig()
    # The poses found so far (T_world_from_query), the prior's guess first if any; those
    # an entry is matched by projection from: one per place (within the joint gates),
    # an entry's pose preferred to the prior's guess.
    found_world = np.empty((n + 1, 4, 4))
    n_found = 0
    seeds = _Seeds(gates)
    votes = _Confirmation(config.fallback_until_confirmed, gates)
    if prior is not None and prior.yaw_rad is not None and refs:
        found_world[0] = _prior_guess(prior, refs[order[0]].T_world_from_cam)
        n_found = 1
        seeds.add(found_world[0], from_entry=False)
        # The filter's prediction is one vote: made without this frame, it confirms the
        # pose once an entry's own correspondences agree with it.
        votes.add(found_world[0])

    def own_ransac(j: int) -> RelativePose:
        ref, pairs = refs[j], matches[j]
        pairs_of[j] = pairs
        pixels, points = keypoints_px[pairs[:, 0]], ref.points_cam[pairs[:, 1]]
        return estimate_relative_pose(pixels, points, intrinsics, config.pnp, rng)

    def solve(j: int, fallback: bool) -> RelativePose:
        nonlocal n_found
        ref = refs[j]
        if not n_found:
            rel = own_ransac(j)
        elif by_projection:
            guesses = invert_rigid(ref.T_world_from_cam) @ seeds.poses_world()
            pairs_of[j], rel = guided_by_projection(
                grid.get(), ref.descriptors, ref.points_cam, guesses, config.pnp, grid.window, rng
            )
            if not rel.accepted and fallback:
                rel = own_ransac(j)
        else:
            pairs = pairs_of[j] = matches[j]
            pixels, points = keypoints_px[pairs[:, 0]], ref.points_cam[pairs[:, 1]]
            # every found pose brought into this entry's frame: T_ref_from_world @ T
            guesses = invert_rigid(ref.T_world_from_cam) @ found_world[:n_found]
            rel = estimate_relative_pose_guided(
                pixels, points, guesses, intrinsics, config.pnp, rng, fallback
            )
        if rel.accepted:
            found_world[n_found] = ref.T_world_from_cam @ rel.T_ref_from_query
            votes.add(found_world[n_found])
            seeds.add(found_world[n_found], from_entry=True)
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
    return [rel for rel in solved if rel is not None], pairs_of


class _Seeds:
    """The poses an entry is matched by projection from: one T_world_from_query per place
    (poses within the joint gates of one already held add nothing), an entry's pose
    taking the place of the prior's guess (a prediction, metres off at worst, whose
    window would miss)."""

    def __init__(self, gates: JointConfig) -> None:
        self.gates = gates
        self.poses: list[np.ndarray] = []
        self.planar: list[np.ndarray] = []
        self.from_entry: list[bool] = []

    def add(self, T_world_from_query: np.ndarray, from_entry: bool) -> None:
        planar = planar_from_T_world_from_cam(T_world_from_query)
        for i, other in enumerate(self.planar):
            near = np.hypot(*(other[:2] - planar[:2])) <= self.gates.position_gate_m
            if near and abs(wrap_angle(other[2] - planar[2])) <= self.gates.yaw_gate_rad:
                if from_entry and not self.from_entry[i]:
                    self.poses[i], self.planar[i], self.from_entry[i] = (
                        T_world_from_query.copy(), planar, True,
                    )  # fmt: skip
                return
        self.poses.append(T_world_from_query.copy())
        self.planar.append(planar)
        self.from_entry.append(from_entry)

    def poses_world(self) -> np.ndarray:
        return np.array(self.poses)


def _refined_by_projection(
    grid: _LazyGrid,
    refs: Sequence[ReferenceEntry],
    matches: Sequence[np.ndarray],
    solved: Sequence[RelativePose],
    config: PoseConfig,
    skip_guided: bool = False,
) -> tuple[list[np.ndarray], list[RelativePose]]:
    """(``skip_guided``: not the guided entries, matched by projection already.) Each
    accepted entry's pose refit on the entry's points matched by projection from
    that pose (the query keypoints near where the pose puts each point compete, instead
    of the whole image), kept when it keeps more inliers. ``matches``: the pairs each
    pose's inliers refer to. Returns the entries' (K, 2) pairs and poses, the refined ones
    replaced."""
    window = config.refine
    assert window is not None
    pairs_out, solved_out = list(matches), list(solved)
    for j, (ref, rel) in enumerate(zip(refs, solved, strict=True)):
        if not rel.accepted or (skip_guided and rel.method == "guided"):
            continue
        refined = refine_by_projection(
            grid.get(), ref.descriptors, ref.points_cam, rel, config.pnp, window
        )
        if refined is not None:
            pairs_out[j], solved_out[j] = refined
    return pairs_out, solved_out


def projection_guided_once(*args, **kwargs):
    """:func:`projection_guided_pose_hypotheses` with ``refit_guided=False``."""
    return projection_guided_pose_hypotheses(*args, **kwargs, refit_guided=False)


PROJECTION_GUIDED_STAGES = FrameStages(
    match=match_on_demand, poses=projection_guided_pose_hypotheses
)
PROJECTION_GUIDED_ONCE_STAGES = FrameStages(match=match_on_demand, poses=projection_guided_once)

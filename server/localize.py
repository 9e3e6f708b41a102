"""Localization of one query frame (docs/method.md section 6): pure, timed stage by stage.

image -> blur + ORB -> VLAD -> k-NN retrieval -> per entry: Hamming matching + PnP RANSAC
-> hypotheses T_world_from_query = T_world_from_ref @ T_ref_from_query.
The map's data come in through two arguments (the index and an entry lookup), so this
module does no I/O and can run against a database, a test fixture or a benchmark.

How entries are retrieved and matched is a named :class:`Preset` (``PRESETS``, picked by
``LocalizeConfig.pipeline``; hloc's ``confs`` are the model). ``"monoloc"`` is the fast
path: the index's Hamming shortlist re-ranked by exact float VLAD distance, and the
numba Hamming matcher. ``"paper"`` is the paper-faithful baseline, for benchmarks: exact
float k-NN over every VLAD of the index (no Hamming shortlist; with a prior, over every
entry inside it; exhaustive while the index is flat, i.e. below
``IndexConfig.ivf_min_entries`` entries) and OpenCV brute-force matching per reference
(same match rule). Features, VLAD, PnP and the answer are the same for both, except
that the paper's pipeline solves every entry with its own RANSAC and adds no joint pose.

PnP (``monoloc``, issue 17): guided. The entries are visited by decreasing number of
matches; the first gets a full RANSAC (none when the retrieval prior carries a heading:
the prior's pose, at the entry's height and tilt, is the first guess), every other entry
is scored against the poses found so far and refined on its own inliers
(``pnp.estimate_relative_pose_guided``). An entry those poses do not explain gets its own
RANSAC only while the pose is unconfirmed: once two entries (or the prior and one entry)
agree, it is rejected without one (``PnpStrategy.fallback_until_confirmed``); the
unexplained entries wait until every entry has been tried, so a confirmation from any of
them spares the others' RANSAC. Every per-entry hypothesis comes from that entry's own
correspondences. Each accepted entry's pose is then refit on the entry's points matched
by projection from it (``vision.projection``: the query keypoints near where the pose
puts each point compete, not the whole image; ``LocalizeConfig.refine_by_projection``),
kept when it keeps more inliers. Then a joint
hypothesis (``vision.joint``): the union of the consistent entries' inliers in the world
frame, refined together; it is appended to the hypotheses, marked ``joint``. A frame
none of whose entries gave a pose gets one RANSAC over all its entries' matches
together (``vision.joint.estimate_pooled_pose``, method ``pooled``; night frames, whose
entries each keep too few matches), refit in turn on the entries' points matched by
projection from it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import invert_rigid, planar_from_T_world_from_cam, wrap_angle
from monoloc.core.prior import RetrievalPrior
from monoloc.server.index.retrieval import RetrievalIndex, SearchResult
from monoloc.server.vision.binary_code import vlad_binary_code
from monoloc.server.vision.features import OrbConfig, extract_features
from monoloc.server.vision.joint import (
    EntryInliers,
    JointConfig,
    PooledConfig,
    best_start,
    consistent_group,
    estimate_joint_pose,
    estimate_pooled_pose,
)
from monoloc.server.vision.matching import (
    MatchConfig,
    match_against_references,
    match_against_references_bruteforce,
)
from monoloc.server.vision.pnp import (
    PnpConfig,
    RelativePose,
    estimate_relative_pose,
    estimate_relative_pose_guided,
    within_threshold,
)
from monoloc.server.vision.pose_covariance import planar_pose_covariance, position_spread_m
from monoloc.server.vision.projection import (
    KeypointGrid,
    ProjectionMatchConfig,
    match_by_projection,
    refine_by_projection,
)
from monoloc.server.vision.vlad import compute_vlad
from monoloc.server.vision.vocabulary import Vocabulary

Retrieve = Callable[
    [RetrievalIndex, np.ndarray, np.ndarray, int, RetrievalPrior | None], SearchResult
]
Match = Callable[[np.ndarray, Sequence[np.ndarray], MatchConfig], list[np.ndarray]]


def retrieve_shortlist(
    index: RetrievalIndex,
    vlad: np.ndarray,
    code: np.ndarray,
    k: int,
    prior: RetrievalPrior | None,
) -> SearchResult:
    """Top-k by the index's own search: Hamming shortlist of the binary codes, exact float
    re-rank (vlad (2048,) float32, code (256,) uint8)."""
    return index.search(vlad, code, k, prior)


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


@dataclass(frozen=True)
class Preset:
    """A named localization pipeline: how entries are retrieved, how the query's
    descriptors are matched against theirs (one (K_r, 2) int32 array per reference), and
    whether PnP may be guided and a joint pose added (``LocalizeConfig`` can turn either
    off, never on for a preset that has them off)."""

    retrieve: Retrieve
    match: Match
    guided: bool = True
    joint: bool = True
    pooled: bool = True


PresetName = Literal["monoloc", "paper"]
PRESETS: dict[PresetName, Preset] = {
    "monoloc": Preset(retrieve_shortlist, match_against_references),
    "paper": Preset(
        retrieve_exhaustive,
        match_against_references_bruteforce,
        guided=False,
        joint=False,
        pooled=False,
    ),
}


@dataclass(frozen=True)
class AlternativeConfig:
    """A second pose for a frame whose hypotheses agree on a poorly pinned pose (a parked
    car that moved between the runs can carry most of every entry's inliers, and ten
    entries then agree on a pose a metre off): one pooled RANSAC (``PooledConfig``) on
    the matches that the most-inlier pose leaves more than ``residual_px`` from their
    projection. Tried only when the median position spread (1 px) of the frame's
    per-entry pose covariances exceeds ``min_spread_m`` (ordinary frames: 0.02-0.05 m on
    dev city 7's street, its moved-car frames 0.07-0.20 m), so an ordinary frame pays
    nothing; kept when it lies at least ``min_offset_m`` from that pose."""

    min_spread_m: float = 0.06
    residual_px: float = 3.0
    min_offset_m: float = 0.1

    def __post_init__(self) -> None:
        if not (self.min_spread_m >= 0 and self.residual_px > 0 and self.min_offset_m >= 0):
            raise InvalidInputError(f"invalid AlternativeConfig {self}")


@dataclass(frozen=True)
class LocalizeConfig:
    """Settings of :func:`localize_frame`; ``pipeline`` names its preset in ``PRESETS``.
    ``refine_by_projection``: the window of the refit of every pose on matches by
    projection (``PnpStrategy.refine``; None: no refit; the paper's preset has none).
    ``pose_covariance``: each per-entry hypothesis's covariance from its inliers
    (``PnpStrategy.covariance``; the "pnp" measurement model's input; not in the paper's
    preset); ``pose_covariance_scales``: each inlier weighed by its keypoint's pyramid
    scale (``PnpStrategy.covariance_scales``). ``alternative``: a second pose for a frame
    whose per-entry poses are poorly pinned down (``AlternativeConfig``; on by default
    since 2026-11-28, with the "pnp" measurement model; none without the pose covariances
    or in a preset without pooled PnP)."""

    orb: OrbConfig = field(default_factory=OrbConfig)
    match: MatchConfig = field(default_factory=MatchConfig)
    pnp: PnpConfig = field(default_factory=PnpConfig)
    k: int = 10
    pipeline: PresetName = "monoloc"
    guided_pnp: bool = True
    guess_from_prior: bool = True
    joint: JointConfig | None = field(default_factory=JointConfig)
    fallback_until_confirmed: int | None = 2
    pooled: PooledConfig | None = field(default_factory=PooledConfig)
    refine_by_projection: ProjectionMatchConfig | None = field(
        default_factory=ProjectionMatchConfig
    )
    pose_covariance: bool = True
    pose_covariance_scales: bool = True
    alternative: AlternativeConfig | None = field(default_factory=AlternativeConfig)

    @property
    def preset(self) -> Preset:
        return PRESETS[self.pipeline]

    @property
    def pnp_strategy(self) -> PnpStrategy:
        """How :func:`pose_hypotheses` runs for this config's preset."""
        preset = self.preset
        return PnpStrategy(
            guided=self.guided_pnp and preset.guided,
            guess_from_prior=self.guess_from_prior and self.guided_pnp and preset.guided,
            joint=self.joint if preset.joint else None,
            fallback_until_confirmed=self.fallback_until_confirmed,
            pooled=self.pooled if preset.pooled else None,
            refine=self.refine_by_projection if preset.guided else None,
            covariance=self.pose_covariance and preset.guided,
            covariance_scales=self.pose_covariance_scales,
            alternative=self.alternative if preset.pooled and self.pose_covariance else None,
        )


@dataclass(frozen=True)
class PnpStrategy:
    """guided: guided PnP (else every entry its own RANSAC, the paper); guess_from_prior:
    a retrieval prior with a heading seeds the guesses; joint: joint-pose settings, None
    for no joint hypothesis.

    fallback_until_confirmed: in guided PnP, an entry the poses found so far do not
    explain gets its own RANSAC only until this many accepted entries agree on one pose
    (within the joint gates, ``JointConfig``'s defaults without a joint pose; a retrieval
    prior with a heading, the filter's prediction, counts as one); after that it is
    rejected without one. None: always its own RANSAC. Why: once independent
    entries confirm a pose, an entry that pose does not explain sees another place (or
    too little of this one), and its own RANSAC could only add a hypothesis that
    contradicts the consensus; on bench/localize.py it ran for about four entries per
    query and accepted none of them, for about a third of the PnP time. Before
    confirmation (e.g. the first entry's RANSAC found a wrong pose) the fallback keeps
    its role.

    pooled: pooled-PnP settings, None for none: a frame none of whose entries gives a
    pose of its own gets one RANSAC on all its entries' matches together
    (``vision.joint.estimate_pooled_pose``; at night an entry often keeps 6-14 matches,
    under ``PnpConfig.min_inliers``, while its neighbours see the same lit facades).

    refine: the projection window (``vision.projection``) on which every accepted entry
    pose, and a pooled pose, is refit on its entries' points matched around where it puts
    them; a refit is kept when it keeps more inliers. None for none. Needs the query's
    descriptors (:func:`pose_hypotheses`' ``descriptors``).

    covariance: give each per-entry hypothesis the Gauss-Newton covariance of its planar
    pose from its own inliers at 1 px (``PoseHypothesis.covariance_px1``,
    ``vision.pose_covariance``: where the inliers lie, which their count does not say).
    Off by default here (``LocalizeConfig.pose_covariance`` turns it on for the
    localizer): it costs ~20 us a hypothesis. covariance_scales: each inlier counts with
    1 px times its query keypoint's pyramid scale (a keypoint found on a coarser ORB level
    is located that much less precisely; ``pose_hypotheses`` then needs the scales).
    """

    guided: bool = True
    guess_from_prior: bool = True
    joint: JointConfig | None = field(default_factory=JointConfig)
    fallback_until_confirmed: int | None = 2
    pooled: PooledConfig | None = field(default_factory=PooledConfig)
    refine: ProjectionMatchConfig | None = field(default_factory=ProjectionMatchConfig)
    covariance: bool = False
    covariance_scales: bool = True
    alternative: AlternativeConfig | None = None

    def __post_init__(self) -> None:
        if self.fallback_until_confirmed is not None and self.fallback_until_confirmed < 1:
            raise InvalidInputError(f"PnpStrategy.fallback_until_confirmed must be >= 1: {self}")
        if self.alternative is not None and (self.pooled is None or not self.covariance):
            raise InvalidInputError(
                f"PnpStrategy.alternative needs pooled PnP and the pose covariances: {self}"
            )


def needs_keypoint_scales(pnp: PnpConfig, strategy: PnpStrategy) -> bool:
    """Whether :func:`pose_hypotheses` uses the query keypoints' pyramid scales: to weigh
    PnP's errors (``PnpConfig.scale_weighting``) or the pose covariance's points
    (``PnpStrategy.covariance_scales``)."""
    return pnp.scale_weighting or (strategy.covariance and strategy.covariance_scales)


@dataclass(frozen=True)
class ReferenceEntry:
    """What localization needs of one map entry: its pose, descriptors and 3D points.

    descriptors (N, 32) uint8 and points_cam (N, 3) float32 in the entry's camera frame.
    """

    entry_id: int
    T_world_from_cam: np.ndarray
    descriptors: np.ndarray
    points_cam: np.ndarray
    tags: tuple[str, ...] = ()

    @property
    def pose_world(self) -> np.ndarray:
        return planar_from_T_world_from_cam(self.T_world_from_cam)

    @classmethod
    def from_entry_data(cls, data) -> ReferenceEntry:
        """From a stored entry (``monoloc.server.storage.records.EntryData``)."""
        return cls(
            entry_id=data.id,
            T_world_from_cam=np.asarray(data.T_world_from_cam),
            descriptors=np.asarray(data.descriptors),
            points_cam=np.asarray(data.points_cam),
            tags=data.summary.tags,
        )


@dataclass(frozen=True)
class PoseHypothesis:
    """One accepted PnP solution against one retrieved entry (docs/method.md s. 6 step 5), or
    the joint pose of several (``joint``; then ``entry_id``, ``entry_pose_world`` and
    ``e_vlad`` are its anchor's, ``entry_ids`` every member, ``n_matches`` / ``n_inliers``
    count the union). method: "ransac", "guided", "joint" or "pooled" (one RANSAC on
    the matches of several entries, for a frame whose entries gave no pose of their own;
    ``entry_ids`` its members; not ``joint``). ``covariance_px1`` (3, 3): the planar
    pose's (X m, Y m, psi rad) covariance from its own inliers at 1 px of pixel noise
    for a full-resolution keypoint (``PnpStrategy.covariance``, ``covariance_scales``;
    None when not asked for, or when the inliers do not determine it; a joint or pooled
    pose's from the inliers of all its entries). ``entry_tags``: the tags of the entry it
    names (a condition's calibration weighs it, ``MeasurementModel.conditions``)."""

    entry_id: int
    T_world_from_cam: np.ndarray
    pose_world: np.ndarray
    entry_pose_world: np.ndarray
    e_vlad: float
    n_matches: int
    n_inliers: int
    reprojection_error_px: float
    joint: bool = False
    entry_ids: tuple[int, ...] = ()
    method: str = "ransac"
    covariance_px1: np.ndarray | None = None
    entry_tags: tuple[str, ...] = ()


@dataclass(frozen=True)
class LocalizationResult:
    hypotheses: list[PoseHypothesis]
    retrieved_ids: np.ndarray
    retrieved_distances: np.ndarray
    rejected: list[tuple[int, str]]
    n_features: int
    timings_ms: dict[str, float]

    @property
    def best(self) -> PoseHypothesis | None:
        """The per-entry hypothesis with the most PnP inliers (the joint one aside)."""
        return max(
            (h for h in self.hypotheses if not h.joint), key=lambda h: h.n_inliers, default=None
        )

    @property
    def joint(self) -> PoseHypothesis | None:
        """The joint hypothesis, if the frame gave one."""
        return next((h for h in self.hypotheses if h.joint), None)


EntryLookup = Callable[[Sequence[int]], Sequence[ReferenceEntry]]


class _Laps:
    """Milliseconds per stage: each ``lap(name)`` times the stage that just ended."""

    def __init__(self) -> None:
        self.start = self.clock = time.perf_counter()
        self.ms: dict[str, float] = {}

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.ms[name], self.clock = (now - self.clock) * 1e3, now

    def total(self) -> dict[str, float]:
        return {**self.ms, "total": (time.perf_counter() - self.start) * 1e3}


def localize_frame(
    image_gray: np.ndarray,
    intrinsics: CameraIntrinsics,
    vocabulary: Vocabulary,
    index: RetrievalIndex,
    lookup_entries: EntryLookup,
    config: LocalizeConfig,
    rng: np.random.Generator,
    prior: RetrievalPrior | None = None,
    k: int | None = None,
) -> LocalizationResult:
    """Hypotheses for one grayscale frame (H, W) uint8 taken with ``intrinsics``."""
    laps, preset = _Laps(), config.preset
    strategy = config.pnp_strategy
    features = extract_features(
        image_gray, config.orb, scales=needs_keypoint_scales(config.pnp, strategy)
    )
    laps.lap("features")
    vlad = compute_vlad(features.descriptors, vocabulary)
    code = vlad_binary_code(vlad)
    laps.lap("vlad")
    found = preset.retrieve(index, vlad, code, k or config.k, prior)
    laps.lap("retrieval")
    by_id = {e.entry_id: e for e in lookup_entries(found.entry_ids.tolist())}
    refs = [by_id[i] for i in found.entry_ids.tolist() if i in by_id]
    laps.lap("lookup")
    matches = preset.match(features.descriptors, [r.descriptors for r in refs], config.match)
    laps.lap("matching")
    e_vlad = dict(zip(found.entry_ids.tolist(), found.distances.tolist(), strict=True))
    hypotheses, rejected = pose_hypotheses(
        features.keypoints_px,
        refs,
        matches,
        e_vlad,
        intrinsics,
        config.pnp,
        rng,
        strategy,
        prior,
        features.scales,
        features.descriptors,
    )
    laps.lap("pnp")
    return LocalizationResult(
        hypotheses=hypotheses,
        retrieved_ids=found.entry_ids,
        retrieved_distances=found.distances,
        rejected=rejected,
        n_features=len(features.descriptors),
        timings_ms=laps.total(),
    )


def pose_hypotheses(
    keypoints_px: np.ndarray,
    refs: Sequence[ReferenceEntry],
    matches: Sequence[np.ndarray],
    e_vlad: dict[int, float],
    intrinsics: CameraIntrinsics,
    config: PnpConfig,
    rng: np.random.Generator,
    strategy: PnpStrategy = PnpStrategy(),
    prior: RetrievalPrior | None = None,
    keypoint_scales: np.ndarray | None = None,
    descriptors: np.ndarray | None = None,
) -> tuple[list[PoseHypothesis], list[tuple[int, str]]]:
    """PnP against each reference (its (K, 2) query/reference index pairs into
    ``keypoints_px`` (N, 2) and its points), guided or not, plus the joint hypothesis
    (appended last). ``keypoint_scales`` (N,): the keypoints' pyramid scales
    (``Features.scales``; None: all at full resolution), which weigh their errors
    (``PnpConfig``). ``descriptors`` (N, 32) uint8: the keypoints' descriptors, for the
    refit by projection (``strategy.refine``; InvalidInputError without them). Returns
    the hypotheses in the references' order and (entry id, reason) of the rejected
    references."""
    keypoints_px = np.asarray(keypoints_px, dtype=np.float64)  # once, not per entry
    scales = None if keypoint_scales is None else np.asarray(keypoint_scales, dtype=np.float64)
    if scales is not None and scales.shape != (len(keypoints_px),):
        raise InvalidInputError(
            f"{len(keypoints_px)} keypoints but keypoint scales of shape {scales.shape}"
        )
    solved = _solve_entries(
        keypoints_px, refs, matches, intrinsics, config, rng, strategy, prior, scales
    )
    pairs_used = matches
    if strategy.refine is not None:
        if descriptors is None:
            raise InvalidInputError("refining by projection needs the query's descriptors")
        pairs_used, solved = _refined_by_projection(
            keypoints_px, descriptors, refs, matches, solved, intrinsics, config,
            strategy.refine, scales,
        )  # fmt: skip
    hypotheses: list[PoseHypothesis] = []
    rejected: list[tuple[int, str]] = []
    inliers: list[EntryInliers] = []
    near_misses: list[np.ndarray] = []  # T_world_from_query of poses short of min_inliers
    for ref, pairs, rel in zip(refs, pairs_used, solved, strict=True):
        if not rel.accepted:
            rejected.append((ref.entry_id, rel.reject_reason or "rejected"))
            if (
                strategy.pooled is not None
                and strategy.pooled.near_miss_guesses
                and rel.n_inliers >= strategy.pooled.guess_min_inliers
                and np.isfinite(rel.T_ref_from_query[0, 0])
            ):
                near_misses.append(ref.T_world_from_cam @ rel.T_ref_from_query)
            continue
        # compose_hypothesis without its rigidity checks: entry poses are checked when
        # stored (storage.entry_checks) and an accepted pose is finite and rigid by
        # construction; the checks cost more than the rest of this loop.
        T_world_from_query = np.asarray(ref.T_world_from_cam, dtype=np.float64) @ (
            rel.T_ref_from_query
        )
        kept = pairs[rel.inlier_mask]
        covariance = None
        if strategy.covariance:
            T_world_from_ref = np.asarray(ref.T_world_from_cam, dtype=np.float64)
            points_world = ref.points_cam[kept[:, 1]] @ T_world_from_ref[:3, :3].T
            covariance = _pose_covariance(
                strategy,
                T_world_from_query,
                points_world + T_world_from_ref[:3, 3],
                None if scales is None else scales[kept[:, 0]],
                intrinsics,
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
                covariance_px1=covariance,
                entry_tags=ref.tags,
            )
        )
        inliers.append(
            EntryInliers(
                ref.T_world_from_cam,
                keypoints_px[kept[:, 0]],
                ref.points_cam[kept[:, 1]],
                None if scales is None else scales[kept[:, 0]],
            )
        )
    if strategy.joint is not None:
        joint = _joint_hypothesis(hypotheses, inliers, intrinsics, config, strategy)
        if joint is not None:
            hypotheses.append(joint)
    if strategy.pooled is not None and not hypotheses and refs:
        pooled = _pooled_hypothesis(
            keypoints_px,
            refs,
            matches,
            e_vlad,
            intrinsics,
            config,
            rng,
            strategy,
            scales,
            near_misses,
        )
        if pooled is not None and strategy.refine is not None:
            assert descriptors is not None  # checked above
            pooled = _refined_pooled(
                pooled, keypoints_px, descriptors, refs, e_vlad, intrinsics, config, rng,
                strategy, scales,
            )  # fmt: skip
        if pooled is not None:
            hypotheses.append(pooled)
    alternative = strategy.alternative
    if alternative is not None and strategy.pooled is not None:
        if _poorly_pinned(hypotheses, alternative.min_spread_m):
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
            found = _pooled_hypothesis(
                keypoints_px, refs, unexplained, e_vlad, intrinsics, config, rng,
                strategy, scales,
            )  # fmt: skip
            if found is not None and (
                np.linalg.norm(found.pose_world[:2] - consensus.pose_world[:2])
                >= alternative.min_offset_m
            ):
                hypotheses.append(replace(found, method="alternative"))
    return hypotheses, rejected


def _pose_covariance(
    strategy: PnpStrategy,
    T_world_from_query: np.ndarray,
    inlier_points_world: np.ndarray,
    inlier_scales: np.ndarray | None,
    intrinsics: CameraIntrinsics,
) -> np.ndarray | None:
    """A hypothesis's planar pose covariance at 1 px from its inliers' world points (M, 3)
    and their query keypoints' scales (M,) (``PnpStrategy.covariance``,
    ``covariance_scales``); None when the strategy does not ask for it."""
    if not strategy.covariance:
        return None
    weigh = strategy.covariance_scales and inlier_scales is not None
    return planar_pose_covariance(
        T_world_from_query,
        inlier_points_world,
        intrinsics,
        keypoint_scales=inlier_scales if weigh else None,
    )


def _poorly_pinned(hypotheses: Sequence[PoseHypothesis], min_spread_m: float) -> bool:
    """Whether the median position spread (1 px) of the per-entry hypotheses' pose
    covariances exceeds ``min_spread_m`` (``AlternativeConfig``; at least two with one)."""
    spreads = [position_spread_m(h.covariance_px1) for h in hypotheses if not h.joint]
    spreads = [v for v in spreads if np.isfinite(v)]
    return len(spreads) >= 2 and float(np.median(spreads)) > min_spread_m


def _solve_entries(
    keypoints_px: np.ndarray,
    refs: Sequence[ReferenceEntry],
    matches: Sequence[np.ndarray],
    intrinsics: CameraIntrinsics,
    config: PnpConfig,
    rng: np.random.Generator,
    strategy: PnpStrategy,
    prior: RetrievalPrior | None,
    scales: np.ndarray | None = None,
) -> list[RelativePose]:
    """One RelativePose per reference, in the references' order.

    Guided: by decreasing number of matches, each entry seeded by the poses
    (T_world_from_query) found so far (the first, with nothing found yet, gets its own
    RANSAC). An entry those poses do not explain waits; if, once every entry has been
    tried, the pose is still not confirmed (``PnpStrategy.fallback_until_confirmed``),
    the waiting entries are tried again in the same order with the poses found by then,
    each falling back to its own RANSAC while the pose is still unconfirmed.
    """
    solved: list[RelativePose | None] = [None] * len(refs)
    order = sorted(range(len(refs)), key=lambda j: -len(matches[j]))
    # The poses found so far (T_world_from_query), the prior's guess first if any.
    found_world = np.empty((len(refs) + 1, 4, 4))
    n_found = 0
    votes = _Confirmation(strategy)
    if strategy.guess_from_prior and prior is not None and prior.yaw_rad is not None and refs:
        found_world[0] = _prior_guess(prior, refs[order[0]].T_world_from_cam)
        n_found = 1
        # The filter's prediction is one vote: made without this frame, it confirms the
        # pose once an entry's own correspondences agree with it.
        votes.add(found_world[0])
    always = strategy.fallback_until_confirmed is None

    def solve(j: int, fallback: bool) -> RelativePose:
        nonlocal n_found
        ref, pairs = refs[j], matches[j]
        pixels, points = keypoints_px[pairs[:, 0]], ref.points_cam[pairs[:, 1]]
        pair_scales = None if scales is None else scales[pairs[:, 0]]
        if strategy.guided and n_found:
            # every found pose brought into this entry's frame: T_ref_from_world @ T
            guesses = invert_rigid(ref.T_world_from_cam) @ found_world[:n_found]
            rel = estimate_relative_pose_guided(
                pixels, points, guesses, intrinsics, config, rng, fallback, pair_scales
            )
        else:
            rel = estimate_relative_pose(pixels, points, intrinsics, config, rng, pair_scales)
        if rel.accepted and strategy.guided:
            found_world[n_found] = ref.T_world_from_cam @ rel.T_ref_from_query
            votes.add(found_world[n_found])
            n_found += 1
        solved[j] = rel
        return rel

    waiting = []
    for j in order:
        rel = solve(j, fallback=always)
        if not rel.accepted and rel.method == "guided":  # not explained, no RANSAC yet
            waiting.append(j)
    if not votes.confirmed:
        for j in waiting:  # with the poses found by then; own RANSAC while unconfirmed
            solve(j, fallback=not votes.confirmed)
    return [rel for rel in solved if rel is not None]


class _Confirmation:
    """Whether ``strategy.fallback_until_confirmed`` accepted poses agree on one pose."""

    def __init__(self, strategy: PnpStrategy) -> None:
        self.needed = strategy.fallback_until_confirmed
        self.gates = strategy.joint or JointConfig()
        self.poses_world: list[np.ndarray] = []
        self.confirmed = False

    def add(self, T_world_from_query: np.ndarray) -> None:
        if self.needed is None or self.confirmed:
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


def _pooled_hypothesis(
    keypoints_px: np.ndarray,
    refs: Sequence[ReferenceEntry],
    matches: Sequence[np.ndarray],
    e_vlad: dict[int, float],
    intrinsics: CameraIntrinsics,
    pnp: PnpConfig,
    rng: np.random.Generator,
    strategy: PnpStrategy,
    keypoint_scales: np.ndarray | None = None,
    guesses_T_world_from_cam: Sequence[np.ndarray] = (),
    fallback: bool = True,
) -> PoseHypothesis | None:
    """The pooled pose (``strategy.pooled``) of the frame's entries, as a hypothesis: not
    marked ``joint`` (it stands in for the per-entry hypotheses the frame did not get,
    and the paper's measurement model leaves joint ones out); entry, entry pose and
    e_vlad are those of the member with the most matches; its covariance from the
    pooled inliers (``strategy.covariance``)."""
    assert strategy.pooled is not None
    pose = estimate_pooled_pose(
        keypoints_px,
        [r.T_world_from_cam for r in refs],
        [r.points_cam for r in refs],
        matches,
        intrinsics,
        pnp,
        rng,
        strategy.pooled,
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
        covariance_px1=_pose_covariance(
            strategy,
            pose.T_world_from_cam,
            pose.inlier_points_world,
            pose.inlier_scales,
            intrinsics,
        ),  # fmt: skip
    )


def _refined_by_projection(
    keypoints_px: np.ndarray,
    descriptors: np.ndarray,
    refs: Sequence[ReferenceEntry],
    matches: Sequence[np.ndarray],
    solved: Sequence[RelativePose],
    intrinsics: CameraIntrinsics,
    config: PnpConfig,
    window: ProjectionMatchConfig,
    scales: np.ndarray | None,
) -> tuple[list[np.ndarray], list[RelativePose]]:
    """Each accepted entry's pose refit on the entry's points matched by projection from
    that pose (``vision.projection``: the query keypoints near where the pose puts each
    point compete, instead of the whole image), kept when it keeps more inliers. Returns
    the entries' (K, 2) pairs and poses, the refined ones replaced."""
    pairs_out, solved_out = list(matches), list(solved)
    grid = None
    for j, (ref, rel) in enumerate(zip(refs, solved, strict=True)):
        if not rel.accepted:
            continue
        if grid is None:
            grid = KeypointGrid(keypoints_px, descriptors, intrinsics, window.radius_px)
        refined = refine_by_projection(
            grid, ref.descriptors, ref.points_cam, rel, config, window, scales
        )
        if refined is not None:
            pairs_out[j], solved_out[j] = refined
    return pairs_out, solved_out


def _refined_pooled(
    pooled: PoseHypothesis,
    keypoints_px: np.ndarray,
    descriptors: np.ndarray,
    refs: Sequence[ReferenceEntry],
    e_vlad: dict[int, float],
    intrinsics: CameraIntrinsics,
    config: PnpConfig,
    rng: np.random.Generator,
    strategy: PnpStrategy,
    scales: np.ndarray | None,
) -> PoseHypothesis:
    """The pooled pose refit on every entry's points matched by projection from it (as
    each entry's own pose is): the pooled pose chooses the consensus set of those matches
    and is refit on it, with pooled PnP's rules (``min_inliers``, at least two entries
    keeping their share); kept when it keeps more inliers, else the pooled pose as it
    was. No RANSAC on these matches: they were chosen around the pooled pose."""
    assert strategy.refine is not None and strategy.pooled is not None
    grid = KeypointGrid(keypoints_px, descriptors, intrinsics, strategy.refine.radius_px)
    T_query_from_world = invert_rigid(pooled.T_world_from_cam)
    matches = [
        match_by_projection(
            grid,
            ref.descriptors,
            ref.points_cam,
            T_query_from_world @ ref.T_world_from_cam,
            strategy.refine,
        )  # fmt: skip
        for ref in refs
    ]
    refined = _pooled_hypothesis(
        keypoints_px,
        refs,
        matches,
        e_vlad,
        intrinsics,
        config,
        rng,
        strategy,
        scales,
        [pooled.T_world_from_cam],
        fallback=False,
    )
    if refined is None or refined.n_inliers <= pooled.n_inliers:
        return pooled
    return refined


def _joint_hypothesis(
    hypotheses: Sequence[PoseHypothesis],
    inliers: Sequence[EntryInliers],
    intrinsics: CameraIntrinsics,
    pnp: PnpConfig,
    strategy: PnpStrategy,
) -> PoseHypothesis | None:
    """The joint pose (``strategy.joint``) of the largest consistent group of hypotheses,
    refined from the member pose under which the union keeps the most inliers, as a
    hypothesis, with its covariance from the union's inliers (``strategy.covariance``)."""
    config = strategy.joint
    assert config is not None
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
    start = best_start(members, starts, intrinsics, pnp)
    joint = estimate_joint_pose(members, starts[start], intrinsics, pnp, config)
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
        covariance_px1=_pose_covariance(
            strategy,
            joint.T_world_from_cam,
            joint.inlier_points_world,
            joint.inlier_scales,
            intrinsics,
        ),  # fmt: skip
    )

"""Localization of one query frame (METHOD.md section 6): pure, timed stage by stage.

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
(same match rule). Features, VLAD, PnP and the answer are the same for both.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.geometry import planar_from_T_world_from_cam
from monoloc.core.prior import RetrievalPrior
from monoloc.server.index.retrieval import RetrievalIndex, SearchResult
from monoloc.server.vision.binary_code import vlad_binary_code
from monoloc.server.vision.features import Features, OrbConfig, extract_features
from monoloc.server.vision.hypothesis import compose_hypothesis
from monoloc.server.vision.matching import (
    MatchConfig,
    match_against_references,
    match_against_references_bruteforce,
)
from monoloc.server.vision.pnp import PnpConfig, estimate_relative_pose
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
    """A named localization pipeline: how entries are retrieved and how the query's
    descriptors are matched against theirs (one (K_r, 2) int32 array per reference)."""

    retrieve: Retrieve
    match: Match


PresetName = Literal["monoloc", "paper"]
PRESETS: dict[PresetName, Preset] = {
    "monoloc": Preset(retrieve_shortlist, match_against_references),
    "paper": Preset(retrieve_exhaustive, match_against_references_bruteforce),
}


@dataclass(frozen=True)
class LocalizeConfig:
    """Settings of :func:`localize_frame`; ``pipeline`` names its preset in ``PRESETS``."""

    orb: OrbConfig = field(default_factory=OrbConfig)
    match: MatchConfig = field(default_factory=MatchConfig)
    pnp: PnpConfig = field(default_factory=PnpConfig)
    k: int = 10
    pipeline: PresetName = "monoloc"

    @property
    def preset(self) -> Preset:
        return PRESETS[self.pipeline]


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


@dataclass(frozen=True)
class PoseHypothesis:
    """One accepted PnP solution against one retrieved entry (METHOD.md s. 6 step 5)."""

    entry_id: int
    T_world_from_cam: np.ndarray
    pose_world: np.ndarray
    entry_pose_world: np.ndarray
    e_vlad: float
    n_matches: int
    n_inliers: int
    reprojection_error_px: float


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
        """The hypothesis with the most PnP inliers."""
        return max(self.hypotheses, key=lambda h: h.n_inliers, default=None)


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
    features = extract_features(image_gray, config.orb)
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
    hypotheses, rejected = _pose_hypotheses(
        features, refs, matches, e_vlad, intrinsics, config.pnp, rng
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


def _pose_hypotheses(
    features: Features,
    refs: Sequence[ReferenceEntry],
    matches: Sequence[np.ndarray],
    e_vlad: dict[int, float],
    intrinsics: CameraIntrinsics,
    config: PnpConfig,
    rng: np.random.Generator,
) -> tuple[list[PoseHypothesis], list[tuple[int, str]]]:
    """PnP RANSAC against each reference in turn (its (K, 2) query/reference index pairs):
    the accepted hypotheses, and (entry id, reason) of the rejected references."""
    hypotheses: list[PoseHypothesis] = []
    rejected: list[tuple[int, str]] = []
    for ref, pairs in zip(refs, matches, strict=True):
        rel = estimate_relative_pose(
            features.keypoints_px[pairs[:, 0]], ref.points_cam[pairs[:, 1]], intrinsics, config, rng
        )
        if not rel.accepted:
            rejected.append((ref.entry_id, rel.reject_reason or "rejected"))
            continue
        T_world_from_query = compose_hypothesis(ref.T_world_from_cam, rel.T_ref_from_query)
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
            )
        )
    return hypotheses, rejected

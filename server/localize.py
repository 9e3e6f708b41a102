"""Localization of one query frame (METHOD.md section 6): pure, timed stage by stage.

image -> blur + ORB -> VLAD -> k-NN retrieval -> per entry: Hamming matching + PnP RANSAC
-> hypotheses T_world_from_query = T_world_from_ref @ T_ref_from_query.
The map's data come in through two arguments (the index and an entry lookup), so this
module does no I/O and can run against a database, a test fixture or a benchmark.

``LocalizeConfig.pipeline = "paper"`` runs the paper-faithful baseline instead of
monoloc's fast paths, for benchmarks: exact float k-NN over every VLAD of the index (no
Hamming shortlist; with a prior, over every entry inside it; exhaustive while the index
is flat, i.e. below ``IndexConfig.ivf_min_entries`` entries) and OpenCV brute-force
matching per reference (``match_descriptors_bruteforce``, same match rule). Features,
VLAD, PnP and the answer are the same.
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
from monoloc.server.vision.features import OrbConfig, extract_features
from monoloc.server.vision.hypothesis import compose_hypothesis
from monoloc.server.vision.matching import MatchConfig, match_against_references
from monoloc.server.vision.pnp import PnpConfig, estimate_relative_pose
from monoloc.server.vision.vlad import compute_vlad
from monoloc.server.vision.vocabulary import Vocabulary


@dataclass(frozen=True)
class LocalizeConfig:
    orb: OrbConfig = field(default_factory=OrbConfig)
    match: MatchConfig = field(default_factory=MatchConfig)
    pnp: PnpConfig = field(default_factory=PnpConfig)
    k: int = 10
    pipeline: Literal["monoloc", "paper"] = "monoloc"  # see the module docstring


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
    timings: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[name] = (now - clock) * 1e3
        clock = now

    start = clock
    features = extract_features(image_gray, config.orb)
    lap("features")
    vlad = compute_vlad(features.descriptors, vocabulary)
    code = vlad_binary_code(vlad)
    lap("vlad")
    k = k or config.k
    if config.pipeline == "paper":
        # k = every entry: the index ranks them all by exact float VLAD distance.
        found = index.search(vlad, code, max(len(index), 1), prior)
        found = SearchResult(found.entry_ids[:k], found.distances[:k])
    else:
        found = index.search(vlad, code, k, prior)
    lap("retrieval")
    entries = list(lookup_entries(found.entry_ids.tolist()))
    by_id = {e.entry_id: e for e in entries}
    refs = [by_id[i] for i in found.entry_ids.tolist() if i in by_id]
    e_vlad = dict(zip(found.entry_ids.tolist(), found.distances.tolist(), strict=True))
    lap("lookup")
    if config.pipeline == "paper":
        from monoloc.server.vision.matching import match_descriptors_bruteforce

        matches = [
            match_descriptors_bruteforce(features.descriptors, r.descriptors, config.match)
            for r in refs
        ]
    else:
        matches = match_against_references(
            features.descriptors, [r.descriptors for r in refs], config.match
        )
    lap("matching")
    hypotheses: list[PoseHypothesis] = []
    rejected: list[tuple[int, str]] = []
    for ref, pairs in zip(refs, matches, strict=True):
        rel = estimate_relative_pose(
            features.keypoints_px[pairs[:, 0]],
            ref.points_cam[pairs[:, 1]],
            intrinsics,
            config.pnp,
            rng,
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
    lap("pnp")
    timings["total"] = (time.perf_counter() - start) * 1e3
    return LocalizationResult(
        hypotheses=hypotheses,
        retrieved_ids=found.entry_ids,
        retrieved_distances=found.distances,
        rejected=rejected,
        n_features=len(features.descriptors),
        timings_ms=timings,
    )

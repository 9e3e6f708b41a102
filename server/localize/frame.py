"""One query frame through the pipeline (docs/method.md section 6), timed stage by stage:
blur + ORB -> VLAD -> retrieval -> entry lookup -> Hamming matching -> pose stage.

The map comes in through two arguments (the index and an entry lookup), so this module
does no I/O and runs against a database, a test fixture or a benchmark alike. The stages
are functions with fixed signatures (:class:`FrameStages`); the product runs
``PRODUCT_STAGES`` and a benchmark may pass its own baseline stages (bench/lab).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.prior import RetrievalPrior
from monoloc.server.index.retrieval import RetrievalIndex, SearchResult
from monoloc.server.localize.config import LocalizeConfig
from monoloc.server.localize.poses import pose_hypotheses
from monoloc.server.localize.results import (
    EntryLookup,
    LocalizationResult,
    PoseHypothesis,
    ReferenceEntry,
)
from monoloc.server.vision.binary_code import vlad_binary_code
from monoloc.server.vision.features import extract_features
from monoloc.server.vision.matching import MatchConfig, match_against_references
from monoloc.server.vision.undistort import undistort_pixels
from monoloc.server.vision.vlad import compute_vlad
from monoloc.server.vision.vocabulary import Vocabulary

# (index, vlad (2048,) float32, code (256,) uint8, k, prior) -> top-k entries
Retrieve = Callable[
    [RetrievalIndex, np.ndarray, np.ndarray, int, RetrievalPrior | None], SearchResult
]
# (query descriptors (N, 32) uint8, each reference's, config) -> (K_r, 2) int32 pairs each
Match = Callable[[np.ndarray, Sequence[np.ndarray], MatchConfig], list[np.ndarray]]
# the signature of :func:`monoloc.server.localize.poses.pose_hypotheses`
PoseStage = Callable[..., tuple[list[PoseHypothesis], list[tuple[int, str]]]]


def retrieve_shortlist(
    index: RetrievalIndex,
    vlad: np.ndarray,
    code: np.ndarray,
    k: int,
    prior: RetrievalPrior | None,
) -> SearchResult:
    """Top-k by the index's own search: Hamming shortlist of the binary codes, exact float
    re-rank."""
    return index.search(vlad, code, k, prior)


@dataclass(frozen=True)
class FrameStages:
    """How a frame's entries are retrieved, matched and posed."""

    retrieve: Retrieve = retrieve_shortlist
    match: Match = match_against_references
    poses: PoseStage = pose_hypotheses


PRODUCT_STAGES = FrameStages()


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
    stages: FrameStages = PRODUCT_STAGES,
) -> LocalizationResult:
    """Hypotheses for one grayscale frame (H, W) uint8 taken with ``intrinsics`` (with a
    lens distortion, its keypoints are undistorted before PnP)."""
    laps = _Laps()
    features = extract_features(image_gray, config.orb, scales=True)
    keypoints_px = features.keypoints_px
    if intrinsics.distortion is not None:
        # the keypoints a pinhole camera with this K would have seen; the rest is pinhole
        keypoints_px = undistort_pixels(keypoints_px, intrinsics)
        intrinsics = intrinsics.pinhole
    laps.lap("features")
    vlad = compute_vlad(features.descriptors, vocabulary)
    code = vlad_binary_code(vlad)
    laps.lap("vlad")
    found = stages.retrieve(index, vlad, code, k or config.k, prior)
    laps.lap("retrieval")
    by_id = {e.entry_id: e for e in lookup_entries(found.entry_ids.tolist())}
    refs: list[ReferenceEntry] = [by_id[i] for i in found.entry_ids.tolist() if i in by_id]
    laps.lap("lookup")
    matches = stages.match(features.descriptors, [r.descriptors for r in refs], config.match)
    laps.lap("matching")
    e_vlad = dict(zip(found.entry_ids.tolist(), found.distances.tolist(), strict=True))
    hypotheses, rejected = stages.poses(
        keypoints_px,
        refs,
        matches,
        e_vlad,
        intrinsics,
        config.poses,
        rng,
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

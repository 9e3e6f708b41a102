"""What the localization stage takes of a map entry and what it gives back."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from monoloc.core.geometry import planar_from_T_world_from_cam


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


EntryLookup = Callable[[Sequence[int]], Sequence[ReferenceEntry]]


@dataclass(frozen=True)
class PoseHypothesis:
    """One accepted PnP solution against one retrieved entry (docs/method.md s. 6 step 5),
    or a pose of several entries.

    method: "ransac" (the entry's own RANSAC), "guided" (a pose found earlier in the
    frame, refit on this entry's own correspondences), "joint" (the union of the
    consistent entries' inliers; ``joint`` True), "pooled" (one RANSAC on the matches of
    several entries, for a frame whose entries gave no pose of their own) or
    "alternative" (a second pooled pose, see ``AlternativeConfig``). For a pose of several
    entries, ``entry_id``, ``entry_pose_world`` and ``e_vlad`` are its anchor's,
    ``entry_ids`` every member, ``n_matches`` / ``n_inliers`` count the union.
    ``covariance_px1`` (3, 3): the planar pose's (X m, Y m, psi rad) covariance from its
    own inliers at 1 px of pixel noise for a full-resolution keypoint (None when the
    inliers do not determine it). ``entry_tags``: the tags of the entry it names (a
    condition's calibration weighs it, ``MeasurementModel.conditions``)."""

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
    """A frame's hypotheses, its retrieved entries (ids, VLAD distances), the rejected
    entries as (entry id, reason), its feature count and the stages' milliseconds."""

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

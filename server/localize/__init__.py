"""The localization stage: one query frame -> pose hypotheses (docs/method.md section 6).

``frame``     :func:`localize_frame`, the frame pipeline (features, VLAD, retrieval,
              matching, then the pose stage), timed stage by stage; pure: the map comes
              in through an index and an entry lookup.
``poses``     :func:`pose_hypotheses`, the pose stage: guided PnP per entry, refit by
              projection, each pose's covariance.
``combined``  the poses of several entries: joint, pooled, alternative.
``config``    :class:`LocalizeConfig` and its :class:`PoseConfig`, the one config.
``results``   :class:`ReferenceEntry` in, :class:`PoseHypothesis` and
              :class:`LocalizationResult` out.
``in_process`` the in-process Localizer (no HTTP), for the lab and tools.
"""

from monoloc.server.localize.config import AlternativeConfig, LocalizeConfig, PoseConfig
from monoloc.server.localize.frame import FrameStages, localize_frame
from monoloc.server.localize.poses import pose_hypotheses
from monoloc.server.localize.results import (
    EntryLookup,
    LocalizationResult,
    PoseHypothesis,
    ReferenceEntry,
)

__all__ = [
    "AlternativeConfig",
    "EntryLookup",
    "FrameStages",
    "LocalizationResult",
    "LocalizeConfig",
    "PoseConfig",
    "PoseHypothesis",
    "ReferenceEntry",
    "localize_frame",
    "pose_hypotheses",
]

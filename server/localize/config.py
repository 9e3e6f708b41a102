"""The localization stage's one config: :class:`LocalizeConfig` (features, matching, k)
holding :class:`PoseConfig` (the pose stage: PnP, refit by projection, joint, pooled
and alternative poses). Defaults are the product's; docs/method.md section 6 says why
each differs from the paper."""

from __future__ import annotations

from dataclasses import dataclass, field

from monoloc.core.errors import InvalidInputError
from monoloc.server.vision.features import OrbConfig
from monoloc.server.vision.joint import JointConfig, PooledConfig
from monoloc.server.vision.matching import MatchConfig
from monoloc.server.vision.pnp import PnpConfig
from monoloc.server.vision.projection import ProjectionMatchConfig


@dataclass(frozen=True)
class AlternativeConfig:
    """A second pose for a frame whose hypotheses agree on a poorly pinned pose (a parked
    car that moved between the runs can carry most of every entry's inliers, and the
    entries then agree on a pose a metre off): one pooled RANSAC on the matches that the
    most-inlier pose leaves more than ``residual_px`` from their projection. Tried only
    when the median position spread (at 1 px) of the frame's per-entry pose covariances
    exceeds ``min_spread_m`` (ordinary frames: 0.02-0.05 m), so an ordinary frame pays
    nothing; kept when it lies at least ``min_offset_m`` from that pose."""

    min_spread_m: float = 0.06
    residual_px: float = 3.0
    min_offset_m: float = 0.1

    def __post_init__(self) -> None:
        if not (self.min_spread_m >= 0 and self.residual_px > 0 and self.min_offset_m >= 0):
            raise InvalidInputError(f"invalid AlternativeConfig {self}")


@dataclass(frozen=True)
class PoseConfig:
    """The pose stage (:func:`monoloc.server.localize.pose_hypotheses`).

    pnp: per-entry PnP RANSAC and guided PnP (``vision.pnp``). fallback_until_confirmed:
    an entry that the poses found so far do not explain gets its own RANSAC only until
    this many accepted entries (the prior's heading counts as one) agree on one pose;
    after that it is rejected without one (once independent entries confirm a pose, an
    entry it does not explain sees another place, and its RANSAC cost about a third of
    the PnP time for no accepted entry). refine: the projection window on which every
    accepted pose, and a pooled one, is refit on its entries' points matched around where
    it puts them (kept when it keeps more inliers). joint: the joint pose over the
    consistent entries' inliers. pooled: one RANSAC over all entries' matches for a frame
    none of whose entries gave a pose (night frames). alternative: see
    :class:`AlternativeConfig`. The sub-stages refine / joint / pooled / alternative may be
    None to leave that step out (ablations in bench/); the product runs them all."""

    pnp: PnpConfig = field(default_factory=PnpConfig)
    fallback_until_confirmed: int = 2
    refine: ProjectionMatchConfig | None = field(default_factory=ProjectionMatchConfig)
    joint: JointConfig | None = field(default_factory=JointConfig)
    pooled: PooledConfig | None = field(default_factory=PooledConfig)
    alternative: AlternativeConfig | None = field(default_factory=AlternativeConfig)

    def __post_init__(self) -> None:
        if self.fallback_until_confirmed < 1:
            raise InvalidInputError(f"PoseConfig.fallback_until_confirmed must be >= 1: {self}")
        if self.alternative is not None and self.pooled is None:
            raise InvalidInputError(f"PoseConfig.alternative needs pooled PnP: {self}")


@dataclass(frozen=True)
class LocalizeConfig:
    """Settings of :func:`monoloc.server.localize.localize_frame`: ORB, Hamming matching,
    ``k`` retrieved entries (docs/method.md section 6) and the pose stage."""

    orb: OrbConfig = field(default_factory=OrbConfig)
    match: MatchConfig = field(default_factory=MatchConfig)
    k: int = 10
    poses: PoseConfig = field(default_factory=PoseConfig)

    def __post_init__(self) -> None:
        if self.k < 1:
            raise InvalidInputError(f"LocalizeConfig.k must be >= 1: {self}")

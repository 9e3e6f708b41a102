"""The in-process Localizer: the server's pipeline (``localize_frame``) called directly
on a retrieval index and an entry lookup, no HTTP, no database. It answers like the
remote localizers of ``monoloc.client.localizer``, so the vehicle's loop
(``monoloc.client.tracking``) runs unchanged against it (bench.lab.evaluation does)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monoloc.client.api import LocalizeAnswer
from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.core.measurement import Hypotheses
from monoloc.core.prior import RetrievalPrior
from monoloc.server.index.retrieval import RetrievalIndex
from monoloc.server.localize.config import LocalizeConfig
from monoloc.server.localize.frame import PRODUCT_STAGES, FrameStages, localize_frame
from monoloc.server.localize.results import EntryLookup, LocalizationResult
from monoloc.server.vision.vocabulary import Vocabulary


@dataclass(frozen=True)
class InProcessAnswer(LocalizeAnswer):
    """A LocalizeAnswer that keeps the pipeline's full result (retrieved entries,
    rejections, PnP details)."""

    result: LocalizationResult | None = None

    @property
    def best_pose_world(self) -> np.ndarray:
        best = self.result.best if self.result is not None else None
        return np.full(3, np.nan) if best is None else best.pose_world


_NO_COVARIANCE = np.full((3, 3), np.nan)


def hypotheses_of(result: LocalizationResult) -> Hypotheses:
    """The filter's view of a result: planar poses, entry poses, VLAD distances and the
    quality features (inliers, reprojection error, joint or not, the pose covariance at
    1 px; NaN where a hypothesis has none), the entries' tags and how each pose was found."""
    if not result.hypotheses:
        return Hypotheses.empty()
    hyps = result.hypotheses
    return Hypotheses(
        np.array([h.pose_world for h in hyps]),
        np.array([h.entry_pose_world for h in hyps]),
        np.array([h.e_vlad for h in hyps]),
        n_inliers=np.array([h.n_inliers for h in hyps], dtype=np.float64),
        reprojection_error_px=np.array([h.reprojection_error_px for h in hyps]),
        joint=np.array([h.joint for h in hyps], dtype=bool),
        pose_covariance=np.array(
            [
                np.full((3, 3), np.nan) if h.covariance_px1 is None else h.covariance_px1
                for h in hyps
            ]
        ),
        entry_tags=tuple(tuple(h.entry_tags) for h in hyps),
        method=tuple(h.method for h in hyps),
    )


class InProcessLocalizer:
    """Localize frames taken with ``intrinsics`` against ``index`` + ``lookup``; RANSAC
    draws from ``rng``, one generator for every call (so answers depend on call order).
    ``stages``: the product's unless a benchmark compares a baseline (bench/lab)."""

    def __init__(
        self,
        index: RetrievalIndex,
        lookup: EntryLookup,
        vocabulary: Vocabulary,
        intrinsics: CameraIntrinsics,
        rng: np.random.Generator,
        config: LocalizeConfig = LocalizeConfig(),
        stages: FrameStages = PRODUCT_STAGES,
    ) -> None:
        self.index = index
        self.lookup = lookup
        self.vocabulary = vocabulary
        self.intrinsics = intrinsics
        self.rng = rng
        self.config = config
        self.stages = stages

    def localize(
        self,
        image: np.ndarray | bytes,
        prior: RetrievalPrior | None = None,
        k: int | None = None,
    ) -> InProcessAnswer:
        """``image``: grayscale (H, W) uint8, or PNG/JPEG bytes."""
        image_gray = _gray(image) if isinstance(image, bytes | bytearray) else image
        result = localize_frame(
            image_gray,
            self.intrinsics,
            self.vocabulary,
            self.index,
            self.lookup,
            self.config,
            self.rng,
            prior,
            k,
            self.stages,
        )
        return InProcessAnswer(hypotheses_of(result), None, result.timings_ms, {}, result=result)


def _gray(data: bytes | bytearray) -> np.ndarray:
    import cv2

    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise InvalidInputError("the image is not a decodable PNG or JPEG")
    return image

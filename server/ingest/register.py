"""Registering a run to the map it is added to (``monoloc.core.registration``): measure
where the map puts a sample of the run's frames, then move the run's written poses by the
smoothed correction before its entries are built.

The measurement localizes each sampled frame against the map's entries from other runs
(an index the caller builds), with a retrieval prior around the frame's written pose, and
takes the joint hypothesis (else the one with the most inliers) as where the map puts it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from monoloc.core.geometry import planar_from_T_world_from_cam
from monoloc.core.prior import RetrievalPrior
from monoloc.core.registration import RegistrationConfig, RunCorrection, run_correction
from monoloc.server.index.retrieval import RetrievalIndex
from monoloc.server.localize import LocalizeConfig, ReferenceEntry, localize_frame
from monoloc.server.vision.vocabulary import Vocabulary


@dataclass(frozen=True)
class RegistrationTarget:
    """The map's entries a run is registered to: their retrieval index, a lookup of their
    data by id (both thread-safe) and the map's vocabulary."""

    vocabulary: Vocabulary
    index: RetrievalIndex
    lookup: Callable[[Sequence[int]], list[ReferenceEntry]]


def measure_offsets(
    source,
    target: RegistrationTarget,
    rng: np.random.Generator,
    config: RegistrationConfig = RegistrationConfig(),
    localize: LocalizeConfig = LocalizeConfig(),
    should_stop: Callable[[], bool] | None = None,
    workers: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """(times (M,) s, offsets (M, 2) m, world x / y: localized minus written) of the
    sampled frames of ``source`` that localized against ``target``; frames without a
    hypothesis give none. ``workers`` threads localize, each frame with its own generator
    spawned from ``rng`` (so the result does not depend on the number of threads)."""
    frames = source.frames[:: config.every]
    if len(target.index) == 0 or not frames:
        return np.zeros(0), np.zeros((0, 2))

    def measure(frame, frame_rng) -> np.ndarray | None:
        if should_stop is not None and should_stop():
            return None
        written = planar_from_T_world_from_cam(frame.T_world_from_cam)
        prior = RetrievalPrior(
            float(written[0]),
            float(written[1]),
            config.search_radius_m,
            float(written[2]),
            config.yaw_tolerance_rad,
        )
        image = source.load(frame).image_gray
        result = localize_frame(
            image,
            source.intrinsics,
            target.vocabulary,
            target.index,
            target.lookup,
            localize,
            frame_rng,
            prior,
            config.k,
        )
        if not result.hypotheses:
            return None
        joint = [h for h in result.hypotheses if h.joint]
        best = joint[0] if joint else max(result.hypotheses, key=lambda h: h.n_inliers)
        return np.asarray(best.pose_world[:2], dtype=np.float64) - written[:2]

    rngs = rng.spawn(len(frames))
    if workers > 1:
        with ThreadPoolExecutor(workers, initializer=_one_cv2_thread) as pool:
            measured = list(pool.map(measure, frames, rngs))
    else:
        measured = [measure(f, r) for f, r in zip(frames, rngs, strict=True)]
    kept = [(f.timestamp_s, d) for f, d in zip(frames, measured, strict=True) if d is not None]
    times = np.array([t for t, _ in kept], dtype=np.float64)
    return times, np.array([d for _, d in kept], dtype=np.float64).reshape(-1, 2)


def _one_cv2_thread() -> None:
    import cv2

    cv2.setNumThreads(1)


def correct_source(source, correction: RunCorrection):
    """A copy of ``source`` whose frames' written positions are moved by the correction
    (world x / y; heights and orientations unchanged)."""
    frames = []
    for frame, offset in zip(source.frames, correction.offsets_m, strict=True):
        T_world_from_cam = np.array(frame.T_world_from_cam, dtype=np.float64, copy=True)
        T_world_from_cam[:2, 3] += offset
        frames.append(dataclasses.replace(frame, T_world_from_cam=T_world_from_cam))
    return dataclasses.replace(source, frames=frames)


def register_source(source, target: RegistrationTarget, rng: np.random.Generator, **options):
    """(corrected source, :class:`RunCorrection`): ``source`` registered to ``target``;
    ``options``: those of :func:`measure_offsets` (config, localize, should_stop, workers)."""
    config = options.get("config", RegistrationConfig())
    times, offsets = measure_offsets(source, target, rng, **options)
    frame_times = np.array([f.timestamp_s for f in source.frames], dtype=np.float64)
    correction = run_correction(frame_times, times, offsets, config)
    return correct_source(source, correction), correction

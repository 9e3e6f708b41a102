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

import numpy as np

from monoloc.core.geometry import planar_from_T_world_from_cam
from monoloc.core.prior import RetrievalPrior
from monoloc.core.registration import RegistrationConfig, RunCorrection, run_correction
from monoloc.server.localize import LocalizeConfig, ReferenceEntry, localize_frame
from monoloc.server.vision.vocabulary import Vocabulary


def measure_offsets(
    source,
    vocabulary: Vocabulary,
    index,
    lookup: Callable[[Sequence[int]], list[ReferenceEntry]],
    rng: np.random.Generator,
    config: RegistrationConfig = RegistrationConfig(),
    localize: LocalizeConfig = LocalizeConfig(),
    should_stop: Callable[[], bool] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(times (M,) s, offsets (M, 2) m, world x / y: localized minus written) of the
    sampled frames of ``source`` that localized; frames without a hypothesis give none.
    ``index`` / ``lookup``: the map's entries the run is registered to."""
    times, offsets = [], []
    if len(index) == 0:
        return np.zeros(0), np.zeros((0, 2))
    for frame in source.frames[:: config.every]:
        if should_stop is not None and should_stop():
            break
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
            image, source.intrinsics, vocabulary, index, lookup, localize, rng, prior, config.k
        )
        if not result.hypotheses:
            continue
        joint = [h for h in result.hypotheses if h.joint]
        best = joint[0] if joint else max(result.hypotheses, key=lambda h: h.n_inliers)
        times.append(frame.timestamp_s)
        offsets.append(np.asarray(best.pose_world[:2], dtype=np.float64) - written[:2])
    return np.asarray(times, dtype=np.float64), np.asarray(offsets).reshape(-1, 2)


def correct_source(source, correction: RunCorrection):
    """A copy of ``source`` whose frames' written positions are moved by the correction
    (world x / y; heights and orientations unchanged)."""
    frames = []
    for frame, offset in zip(source.frames, correction.offsets_m, strict=True):
        T_world_from_cam = np.array(frame.T_world_from_cam, dtype=np.float64, copy=True)
        T_world_from_cam[:2, 3] += offset
        frames.append(dataclasses.replace(frame, T_world_from_cam=T_world_from_cam))
    return dataclasses.replace(source, frames=frames)


def register_source(
    source,
    vocabulary: Vocabulary,
    index,
    lookup: Callable[[Sequence[int]], list[ReferenceEntry]],
    rng: np.random.Generator,
    config: RegistrationConfig = RegistrationConfig(),
    localize: LocalizeConfig = LocalizeConfig(),
    should_stop: Callable[[], bool] | None = None,
):
    """(corrected source, :class:`RunCorrection`): ``source`` registered to the map."""
    times, offsets = measure_offsets(
        source, vocabulary, index, lookup, rng, config, localize, should_stop
    )
    frame_times = np.array([f.timestamp_s for f in source.frames], dtype=np.float64)
    correction = run_correction(frame_times, times, offsets, config)
    return correct_source(source, correction), correction

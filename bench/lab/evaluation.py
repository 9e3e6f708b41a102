"""In-process evaluation of the method on recorded runs (the benchmark's engine).

The map is built in memory with the server's own code (entry builder, retrieval index,
localization pipeline), answered by the in-process localizer; the vehicle side is the
vehicle's own loop (monoloc.client.tracking). No HTTP and no database, so variants of
the method can be compared quickly on the same frames:

- full:        particle filter + prior-constrained retrieval (the product);
- full_mode:   the same reporting the particles' main mode (docs/method.md's estimate) instead
               of the Gaussian filter riding on it (``FilterConfig.refine``);
- kidnapped:   the full method with the filter initialised ``kidnap_offset_m`` to the
               left of the first pose: how long it takes to find its way back;
- no_prior:    particle filter, retrieval always over the whole map;
- top1:        retrieval only, pose of the top retrieved entry;
- topk_mean:   retrieval only, mean pose of the top-k entries (the paper's "blue points");
- best_pnp:    the best single PnP hypothesis per frame, no filter.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from monoloc.client.api import LocalizeAnswer
from monoloc.client.localizer import Localizer
from monoloc.client.particle_filter import FilterConfig
from monoloc.client.tracking import PriorConfig, Tracker
from monoloc.client.trajectory import TrajectoryMetrics, trajectory_metrics
from monoloc.core.geometry import circular_mean, planar_from_T_world_from_cam
from monoloc.core.measurement import MeasurementModel
from monoloc.core.prior import RetrievalPrior
from monoloc.core.registration import RegistrationConfig, RunCorrection
from monoloc.server.entry_builder import BuildConfig, TooFewPointsError, build_entry
from monoloc.server.index.retrieval import RetrievalIndex
from monoloc.server.ingest.register import RegistrationTarget, register_source
from monoloc.server.localize import (
    LocalizationResult,
    LocalizeConfig,
    ReferenceEntry,
    localize_frame,
)
from monoloc.server.localize.frame import PRODUCT_STAGES, FrameStages
from monoloc.server.localize.in_process import InProcessAnswer, InProcessLocalizer
from monoloc.server.vision.vocabulary import Vocabulary

Progress = Callable[[int, int], None] | None


@dataclass
class MemoryMap:
    """A map held in memory: retrieval index + reference entries, keyed by entry id."""

    index: RetrievalIndex
    refs: dict[int, ReferenceEntry]
    poses_world: dict[int, np.ndarray]
    vocabulary: Vocabulary
    skipped: int = 0
    corrections: list[RunCorrection] = field(default_factory=list)  # of registered runs

    def lookup(self, ids: Sequence[int]) -> list[ReferenceEntry]:
        return [self.refs[i] for i in ids if i in self.refs]

    def add_run(
        self,
        seq,
        config: BuildConfig = BuildConfig(),
        tags: tuple[str, ...] = (),
        progress: Progress = None,
        every: int = 1,
        register: RegistrationConfig | None = None,
    ) -> int:
        """Add every ``every``-th frame of a KittiSequence / TumRun; returns entries added.
        ``register``: first register the run to the entries already held (as the server's
        ingestion does; the correction is appended to ``corrections``)."""
        if register is not None:
            target = RegistrationTarget(self.vocabulary, self.index, self.lookup)
            seq, correction = register_source(
                seq, target, np.random.default_rng(0), config=register
            )
            self.corrections.append(correction)
        next_id = max(self.refs, default=-1) + 1
        ids, codes, vlads, poses = [], [], [], []
        frames = seq.frames[::every]
        for n, frame in enumerate(frames):
            loaded = seq.load(frame)
            try:
                entry = build_entry(
                    loaded.image_gray,
                    f"{seq.name}:{frame.index}",
                    frame.T_world_from_cam,
                    loaded.source,
                    seq.intrinsics,
                    self.vocabulary,
                    None,
                    config,
                    tags,
                )
            except TooFewPointsError:
                self.skipped += 1
                continue
            entry_id = next_id + len(ids)
            self.refs[entry_id] = ReferenceEntry(
                entry_id, entry.T_world_from_cam, entry.descriptors, entry.points_cam, tags
            )
            self.poses_world[entry_id] = planar_from_T_world_from_cam(entry.T_world_from_cam)
            ids.append(entry_id)
            codes.append(entry.code)
            vlads.append(entry.vlad)
            poses.append(self.poses_world[entry_id])
            if progress:
                progress(n + 1, len(frames))
        if ids:
            self.index.add(np.array(ids), np.stack(codes), np.stack(vlads), np.stack(poses))
        return len(ids)

    @classmethod
    def empty(cls, vocabulary: Vocabulary) -> MemoryMap:
        return cls(RetrievalIndex(), {}, {}, vocabulary)


@dataclass(frozen=True)
class EvalConfig:
    localize: LocalizeConfig = field(default_factory=LocalizeConfig)
    # the localization stage's stages: the product's, or a baseline's (bench.lab.paper)
    stages: FrameStages = PRODUCT_STAGES
    filter: FilterConfig = field(default_factory=FilterConfig)
    prior: PriorConfig = field(default_factory=PriorConfig)
    seed: int = 0
    kidnap_offset_m: float = 30.0


@dataclass
class RunEvaluation:
    """Per-frame planar estimates (N, 3) of each variant, metrics and stage timings.

    ``hypotheses_world`` (N lists of (H, 3)) and ``likeliest_world`` (N, 3; NaN without
    hypotheses) are the server's answers to the main variant ("full", else the global
    search): what the filter was given, for the best-of-k and likeliest figures.
    """

    truth_world: np.ndarray
    estimates: dict[str, np.ndarray]
    metrics: dict[str, TrajectoryMetrics]
    timings_ms: list[dict[str, float]]
    n_hypotheses: np.ndarray
    timestamps_s: np.ndarray
    hypotheses_world: list[np.ndarray]
    likeliest_world: np.ndarray
    reseeds: dict[str, int] = field(default_factory=dict)


FILTER_VARIANTS = ("full", "full_mode", "kidnapped", "no_prior")
GLOBAL_VARIANTS = ("no_prior", "top1", "topk_mean", "best_pnp")


def _retrieval_poses(memory: MemoryMap, result: LocalizationResult):
    ids = result.retrieved_ids.tolist()
    if not ids:
        return np.full(3, np.nan), np.full(3, np.nan)
    poses = np.array([memory.poses_world[i] for i in ids])
    mean = np.array([poses[:, 0].mean(), poses[:, 1].mean(), circular_mean(poses[:, 2])])
    return poses[0], mean


class _OneGlobalSearch:
    """Answers a frame's prior-free queries with that frame's one global search, so the
    variants that need it share it (and the RANSAC draws stay those of one search)."""

    def __init__(self, localizer: Localizer, answer: LocalizeAnswer | None) -> None:
        self.localizer, self.answer = localizer, answer

    def localize(
        self, image, prior: RetrievalPrior | None = None, k: int | None = None
    ) -> LocalizeAnswer:
        if prior is None and k is None and self.answer is not None:
            return self.answer
        return self.localizer.localize(image, prior, k)


def _trackers(
    seq,
    signals: np.ndarray,
    model: MeasurementModel,
    config: EvalConfig,
    lever_arm_m: float,
    variants: Sequence[str],
    start_world: np.ndarray,
) -> dict[str, Tracker]:
    """The vehicle's loop for each filter variant asked for, one filter (same seed) each;
    the kidnapped one starts initialised off ``start_world`` (3,)."""
    times = np.array([f.timestamp_s for f in seq.frames])
    motion = replace(config.filter.motion, lever_arm_m=lever_arm_m)
    fconf = replace(config.filter, motion=motion)
    configs = {"full_mode": replace(fconf, refine=None)}
    trackers = {
        v: Tracker(
            configs.get(v, fconf),
            model,
            np.random.default_rng(config.seed),
            times,
            signals,
            config.prior,
            use_prior=v != "no_prior",
        )
        for v in FILTER_VARIANTS
        if v in variants
    }
    if "kidnapped" in trackers:
        yaw = start_world[2]
        left = config.kidnap_offset_m * np.array([-math.sin(yaw), math.cos(yaw), 0.0])
        trackers["kidnapped"].filter.initialise(
            start_world + left, config.filter.init_position_std_m, config.filter.init_yaw_std_rad
        )
    return trackers


def _record_global(
    memory: MemoryMap, est: dict[str, np.ndarray], i: int, answer: InProcessAnswer
) -> None:
    """The retrieval-only and best-PnP variants' pose of frame i from its global search."""
    result = answer.result
    top1, topk = _retrieval_poses(memory, result)
    if "top1" in est:
        est["top1"][i] = top1
    if "topk_mean" in est:
        est["topk_mean"][i] = topk
    if "best_pnp" in est and result.best is not None:
        est["best_pnp"][i] = result.best.pose_world


def evaluate_run(
    memory: MemoryMap,
    seq,
    signals: np.ndarray,
    model: MeasurementModel,
    config: EvalConfig = EvalConfig(),
    lever_arm_m: float = 0.0,
    variants: Sequence[str] = ("full", "no_prior", "top1", "topk_mean", "best_pnp"),
    progress: Progress = None,
) -> RunEvaluation:
    """Localize every frame of ``seq`` (KittiSequence / TumRun) with each variant.

    ``signals`` (N, 2): measured speed and yaw rate per frame (vehicle.txt).
    """
    unknown = set(variants) - {*FILTER_VARIANTS, *GLOBAL_VARIANTS}
    if unknown:
        raise ValueError(f"unknown variants {sorted(unknown)}")
    n = seq.n_frames
    truth = np.array([planar_from_T_world_from_cam(f.T_world_from_cam) for f in seq.frames])
    trackers = _trackers(seq, signals, model, config, lever_arm_m, variants, truth[0])
    localizer = InProcessLocalizer(
        memory.index,
        memory.lookup,
        memory.vocabulary,
        seq.intrinsics,
        np.random.default_rng(config.seed + 1),
        config.localize,
        config.stages,
    )
    est = {v: np.full((n, 3), np.nan) for v in variants if v not in trackers}
    timings, n_hyp = [], np.zeros(n, dtype=np.int64)
    hypotheses, likeliest = [], np.full((n, 3), np.nan)
    need_global = any(v in variants for v in GLOBAL_VARIANTS)
    for i, frame in enumerate(seq.frames):
        image = seq.load(frame).image_gray
        search: InProcessAnswer | None = localizer.localize(image) if need_global else None
        answers = {
            v: t.follow(i, image, _OneGlobalSearch(localizer, search)) for v, t in trackers.items()
        }
        main = answers.get("full", search)
        timings.append(main.timings_ms)
        n_hyp[i] = len(main.hypotheses)
        hypotheses.append(np.array(main.hypotheses.pose_world, dtype=np.float64))
        likeliest[i] = main.best_pose_world
        if search is not None:
            _record_global(memory, est, i, search)
        if progress:
            progress(i + 1, n)
    est.update({v: t.estimates_world for v, t in trackers.items()})
    est = {v: est[v] for v in variants}
    metrics = {v: trajectory_metrics(e, truth) for v, e in est.items()}
    times = np.array([f.timestamp_s for f in seq.frames])
    reseeds = {v: t.filter.n_reseeds for v, t in trackers.items()}
    return RunEvaluation(truth, est, metrics, timings, n_hyp, times, hypotheses, likeliest, reseeds)


@dataclass(frozen=True)
class GlobalFrame:
    """One query frame localized without a prior: its index in the run, its written pose
    (3,) (X m, Y m, heading rad), the server's result, and the CPU time (ms, this thread)
    the localization took."""

    index: int
    truth_world: np.ndarray
    result: LocalizationResult
    cpu_ms: float


def localize_globally(
    memory: MemoryMap,
    query,
    config: LocalizeConfig,
    rng: np.random.Generator,
    stages: FrameStages = PRODUCT_STAGES,
) -> Iterator[GlobalFrame]:
    """Every frame of a KittiSequence / TumRun localized against the whole map (no prior),
    in order, with the server's pipeline: what the per-frame benches compare."""
    for index, frame in enumerate(query.frames):
        image = query.load(frame).image_gray
        truth = planar_from_T_world_from_cam(frame.T_world_from_cam)
        started = time.thread_time()
        result = localize_frame(
            image,
            query.intrinsics,
            memory.vocabulary,
            memory.index,
            memory.lookup,
            config,
            rng,
            stages=stages,
        )
        yield GlobalFrame(index, truth, result, (time.thread_time() - started) * 1e3)


def stage_percentiles(timings: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    """p50 / p99 per stage (ms) over frames."""
    stages = sorted({k for t in timings for k in t})
    return {
        s: {
            "p50": float(np.percentile([t[s] for t in timings if s in t], 50)),
            "p99": float(np.percentile([t[s] for t in timings if s in t], 99)),
        }
        for s in stages
    }


def metrics_row(m: TrajectoryMetrics) -> dict[str, float]:
    d = m.to_dict()
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}

"""In-process evaluation of the method on recorded runs (the benchmark's engine).

The map is built in memory with the server's own code (entry builder, retrieval index,
localization pipeline); the vehicle side is the client's filter. No HTTP and no
database, so variants of the method can be compared quickly on the same frames:

- full:        particle filter + prior-constrained retrieval (the product);
- no_prior:    particle filter, retrieval always over the whole map;
- top1:        retrieval only, pose of the top retrieved entry;
- topk_mean:   retrieval only, mean pose of the top-k entries (the paper's "blue points");
- best_pnp:    the best single PnP hypothesis per frame, no filter.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from monoloc.client.drive import PriorConfig, prior_from_filter
from monoloc.client.particle_filter import FilterConfig, ParticleFilter
from monoloc.client.trajectory import TrajectoryMetrics, trajectory_metrics
from monoloc.core.geometry import circular_mean, planar_from_T_world_from_cam
from monoloc.core.measurement import Hypotheses, MeasurementModel
from monoloc.server.entry_builder import BuildConfig, TooFewPointsError, build_entry
from monoloc.server.index.retrieval import RetrievalIndex
from monoloc.server.localize import (
    LocalizationResult,
    LocalizeConfig,
    ReferenceEntry,
    localize_frame,
)
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

    def lookup(self, ids: Sequence[int]) -> list[ReferenceEntry]:
        return [self.refs[i] for i in ids if i in self.refs]

    def add_run(
        self,
        seq,
        config: BuildConfig = BuildConfig(),
        tags: tuple[str, ...] = (),
        progress: Progress = None,
        every: int = 1,
    ) -> int:
        """Add every ``every``-th frame of a KittiSequence / TumRun; returns entries added."""
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
    filter: FilterConfig = field(default_factory=FilterConfig)
    prior: PriorConfig = field(default_factory=PriorConfig)
    seed: int = 0


@dataclass
class RunEvaluation:
    """Per-frame planar estimates (N, 3) of each variant, metrics and stage timings."""

    truth_world: np.ndarray
    estimates: dict[str, np.ndarray]
    metrics: dict[str, TrajectoryMetrics]
    timings_ms: list[dict[str, float]]
    n_hypotheses: np.ndarray


def _hypotheses(result: LocalizationResult) -> Hypotheses:
    if not result.hypotheses:
        return Hypotheses.empty()
    return Hypotheses(
        np.array([h.pose_world for h in result.hypotheses]),
        np.array([h.entry_pose_world for h in result.hypotheses]),
        np.array([h.e_vlad for h in result.hypotheses]),
    )


def _retrieval_poses(memory: MemoryMap, result: LocalizationResult):
    ids = result.retrieved_ids.tolist()
    if not ids:
        return np.full(3, np.nan), np.full(3, np.nan)
    poses = np.array([memory.poses_world[i] for i in ids])
    mean = np.array([poses[:, 0].mean(), poses[:, 1].mean(), circular_mean(poses[:, 2])])
    return poses[0], mean


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
    n = seq.n_frames
    truth = np.array([planar_from_T_world_from_cam(f.T_world_from_cam) for f in seq.frames])
    times = np.array([f.timestamp_s for f in seq.frames])
    motion = replace(config.filter.motion, lever_arm_m=lever_arm_m)
    fconf = replace(config.filter, motion=motion)
    est = {v: np.full((n, 3), np.nan) for v in variants}
    filters = {
        v: ParticleFilter(fconf, model, np.random.default_rng(config.seed))
        for v in ("full", "no_prior")
        if v in variants
    }
    rng = np.random.default_rng(config.seed + 1)
    timings, n_hyp = [], np.zeros(n, dtype=np.int64)
    need_global = any(v in variants for v in ("no_prior", "top1", "topk_mean", "best_pnp"))
    for i, frame in enumerate(seq.frames):
        image = seq.load(frame).image_gray
        for pf in filters.values():
            if i > 0:
                pf.predict(float(times[i] - times[i - 1]), *map(float, signals[i - 1]))
        results = {}
        if need_global:
            results["global"] = localize_frame(
                image,
                seq.intrinsics,
                memory.vocabulary,
                memory.index,
                memory.lookup,
                config.localize,
                rng,
            )
        if "full" in filters:
            prior = prior_from_filter(filters["full"], config.prior)
            if prior is None and "global" in results:
                results["full"] = results["global"]
            else:
                results["full"] = localize_frame(
                    image,
                    seq.intrinsics,
                    memory.vocabulary,
                    memory.index,
                    memory.lookup,
                    config.localize,
                    rng,
                    prior,
                )
        main = results.get("full", results.get("global"))
        timings.append(main.timings_ms)
        n_hyp[i] = len(main.hypotheses)
        for name, pf in filters.items():
            hyps = _hypotheses(results["full" if name == "full" else "global"])
            if not pf.initialised:
                if len(hyps):
                    pf.initialise_from_hypotheses(hyps)
            else:
                pf.update(hyps)
            if pf.initialised:
                est[name][i] = pf.estimate().pose_world
        if "global" in results:
            top1, topk = _retrieval_poses(memory, results["global"])
            if "top1" in est:
                est["top1"][i] = top1
            if "topk_mean" in est:
                est["topk_mean"][i] = topk
            best = results["global"].best
            if "best_pnp" in est and best is not None:
                est["best_pnp"][i] = best.pose_world
        if progress:
            progress(i + 1, n)
    metrics = {v: trajectory_metrics(e, truth) for v, e in est.items()}
    return RunEvaluation(truth, est, metrics, timings, n_hyp)


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

"""Trajectory files (TUM and KITTI formats, readable by evo) and accuracy metrics."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.core.formats import kitti, tum
from monoloc.core.geometry import T_world_from_cam_planar, wrap_angle, zup_to_kitti


def poses_from_planar(planar_world: np.ndarray, height_m: float = 0.0) -> np.ndarray:
    """Level camera poses T_world_from_cam (N, 4, 4) from planar poses (N, 3)."""
    return (
        np.stack([T_world_from_cam_planar(x, y, yaw, height_m) for x, y, yaw in planar_world])
        if len(planar_world)
        else np.zeros((0, 4, 4))
    )


def write_trajectory_files(
    out_prefix: Path, timestamps_s: np.ndarray, planar_world: np.ndarray, height_m: float = 0.0
) -> tuple[Path, Path]:
    """Write ``<prefix>.tum.txt`` (TUM: t x y z qx qy qz qw of T_world_from_cam, z-up world)
    and ``<prefix>.kitti.txt`` (KITTI: 3x4 T_kittiworld_from_cam per line), both readable
    by evo; returns both paths."""
    poses = poses_from_planar(np.asarray(planar_world), height_m)
    out_prefix.parent.mkdir(parents=True, exist_ok=True)
    tum_path = out_prefix.with_name(out_prefix.name + ".tum.txt")
    kitti_path = out_prefix.with_name(out_prefix.name + ".kitti.txt")
    with open(tum_path, "w") as fh:
        tum.write_trajectory(fh, np.asarray(timestamps_s), poses)
    with open(kitti_path, "w") as fh:
        # KITTI's own world (y down, z forward), so the file compares directly with the
        # dataset's poses/NN.txt
        kitti.write_poses(fh, zup_to_kitti(poses))
    return tum_path, kitti_path


@dataclass(frozen=True)
class TrajectoryMetrics:
    """Accuracy of an estimated planar trajectory against ground truth."""

    n_frames: int
    coverage: float  # share of frames with an estimate; RMSE, median and heading use those
    position_rmse_m: float
    position_median_m: float
    heading_rmse_deg: float
    within_0_25m_2deg: float
    within_0_5m_5deg: float
    within_5m_10deg: float

    def to_dict(self) -> dict:
        return asdict(self)


def trajectory_metrics(estimate_world: np.ndarray, truth_world: np.ndarray) -> TrajectoryMetrics:
    """Metrics of planar estimates (N, 3) vs truth (N, 3); NaN rows count as misses."""
    est = np.asarray(estimate_world, dtype=np.float64)
    truth = np.asarray(truth_world, dtype=np.float64)
    if est.shape != truth.shape or est.ndim != 2 or est.shape[1] != 3 or len(est) == 0:
        raise InvalidInputError(f"need matching (N, 3) arrays, got {est.shape} and {truth.shape}")
    valid = np.all(np.isfinite(est), axis=1)
    pos_err = np.full(len(est), np.inf)
    yaw_err = np.full(len(est), np.inf)
    pos_err[valid] = np.linalg.norm(est[valid, :2] - truth[valid, :2], axis=1)
    yaw_err[valid] = np.abs(wrap_angle(est[valid, 2] - truth[valid, 2]))
    yaw_deg = np.degrees(yaw_err)

    def share(max_m: float, max_deg: float) -> float:
        return float(np.mean((pos_err <= max_m) & (yaw_deg <= max_deg)))

    rmse = float(math.sqrt(np.mean(np.square(pos_err[valid])))) if valid.any() else math.inf
    heading = float(math.sqrt(np.mean(np.square(yaw_deg[valid])))) if valid.any() else math.inf
    return TrajectoryMetrics(
        n_frames=len(est),
        coverage=float(np.mean(valid)),
        position_rmse_m=rmse,
        position_median_m=float(np.median(pos_err)),
        heading_rmse_deg=heading,
        within_0_25m_2deg=share(0.25, 2.0),
        within_0_5m_5deg=share(0.5, 5.0),
        within_5m_10deg=share(5.0, 10.0),
    )


def frame_errors(estimate_world: np.ndarray, truth_world: np.ndarray) -> np.ndarray:
    """Per-frame errors (N, 3) of planar estimates (N, 3) against truth (N, 3), in the
    truth's own frame: along-track (m, + ahead), cross-track (m, + to the left) and
    heading (rad, estimate minus truth, wrapped). NaN rows stay NaN."""
    est = np.asarray(estimate_world, dtype=np.float64)
    truth = np.asarray(truth_world, dtype=np.float64)
    if est.shape != truth.shape or est.ndim != 2 or est.shape[1] != 3:
        raise InvalidInputError(f"need matching (N, 3) arrays, got {est.shape} and {truth.shape}")
    d = est[:, :2] - truth[:, :2]
    cos_t, sin_t = np.cos(truth[:, 2]), np.sin(truth[:, 2])
    return np.stack(
        [
            d[:, 0] * cos_t + d[:, 1] * sin_t,
            -d[:, 0] * sin_t + d[:, 1] * cos_t,
            wrap_angle(est[:, 2] - truth[:, 2]),
        ],
        axis=1,
    )


def yaw_rate_of(truth_world: np.ndarray, timestamps_s: np.ndarray) -> np.ndarray:
    """Yaw rate (N,) rad/s of a planar trajectory (N, 3) at its timestamps (N,): central
    differences of the unwrapped heading (one-sided at the ends)."""
    yaw = np.unwrap(np.asarray(truth_world, dtype=np.float64)[:, 2])
    t = np.asarray(timestamps_s, dtype=np.float64)
    if len(yaw) < 2:
        return np.zeros(len(yaw))
    return np.gradient(yaw, t)


@dataclass(frozen=True)
class TurnClasses:
    """Frames by the truth's |yaw rate|: straight below ``turning_radps``, sharp from
    ``sharp_radps`` (a car at 9 m/s turning at 0.3 rad/s pulls 2.7 m/s^2 sideways)."""

    turning_radps: float = 0.05
    sharp_radps: float = 0.3

    def classify(self, yaw_rate_radps: np.ndarray) -> np.ndarray:
        """Class names (N,): "straight", "turning" or "sharp"."""
        rate = np.abs(np.asarray(yaw_rate_radps))
        return np.where(
            rate < self.turning_radps,
            "straight",
            np.where(rate < self.sharp_radps, "turning", "sharp"),
        )


@dataclass(frozen=True)
class SegmentErrors:
    """Signed error means of the frames of one class (estimates present only).

    cross_inward_mean_m: cross-track error towards the centre of the turn (the sign of the
    yaw rate times the cross-track error; an estimate that falls to the outside of turns
    has a negative mean). heading_ahead_mean_deg: heading error in the turning direction.
    """

    n_frames: int
    along_mean_m: float
    cross_mean_m: float
    cross_inward_mean_m: float
    cross_rmse_m: float
    position_median_m: float
    heading_mean_deg: float
    heading_ahead_mean_deg: float
    heading_rmse_deg: float

    def to_dict(self) -> dict:
        return asdict(self)


def errors_by_turning(
    estimate_world: np.ndarray,
    truth_world: np.ndarray,
    timestamps_s: np.ndarray,
    classes: TurnClasses = TurnClasses(),
) -> dict[str, SegmentErrors]:
    """:class:`SegmentErrors` of the "straight", "turning" and "sharp" frames and of "all"
    (a class without frames is left out). NaN estimates are skipped."""
    errors = frame_errors(estimate_world, truth_world)
    yaw_rate = yaw_rate_of(truth_world, timestamps_s)
    names = classes.classify(yaw_rate)
    valid = np.all(np.isfinite(errors), axis=1)
    out = {}
    for name in ("straight", "turning", "sharp", "all"):
        pick = valid & ((names == name) if name != "all" else True)
        if not pick.any():
            continue
        along, cross, heading = errors[pick].T
        sign = np.sign(yaw_rate[pick])
        out[name] = SegmentErrors(
            n_frames=int(pick.sum()),
            along_mean_m=float(along.mean()),
            cross_mean_m=float(cross.mean()),
            cross_inward_mean_m=float(np.mean(sign * cross)),
            cross_rmse_m=float(np.sqrt(np.mean(cross**2))),
            position_median_m=float(np.median(np.hypot(along, cross))),
            heading_mean_deg=float(np.degrees(heading.mean())),
            heading_ahead_mean_deg=float(np.degrees(np.mean(sign * heading))),
            heading_rmse_deg=float(np.degrees(np.sqrt(np.mean(heading**2)))),
        )
    return out


def best_of_k_errors(hypotheses_world: list[np.ndarray], truth_world: np.ndarray) -> np.ndarray:
    """Per frame, the position error (m) of the hypothesis closest to the truth: an
    oracle's pick among the frame's hypotheses ((H, 3) each, H may be 0); (N,), NaN for a
    frame without hypotheses."""
    truth = np.asarray(truth_world, dtype=np.float64)
    if len(hypotheses_world) != len(truth):
        raise InvalidInputError(f"{len(hypotheses_world)} frames of hypotheses, {len(truth)} poses")
    out = np.full(len(truth), np.nan)
    for i, poses in enumerate(hypotheses_world):
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        if len(poses):
            out[i] = float(np.min(np.linalg.norm(poses[:, :2] - truth[i, :2], axis=1)))
    return out


def blurred_best_of_k_errors(
    hypotheses_world: list[np.ndarray],
    truth_world: np.ndarray,
    blur_sigma_m: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """:func:`best_of_k_errors` after moving every hypothesis's position by an isotropic
    Gaussian draw of ``blur_sigma_m`` (m, per axis): a test of the oracle itself. Where
    the truth it is judged by lies off the hypotheses' cluster (recording errors), a
    wider cluster covers more of the offset, so noise that carries no information can
    lower the best of k; an estimator that fuses the hypotheses cannot profit from it."""
    if not (np.isfinite(blur_sigma_m) and blur_sigma_m >= 0.0):
        raise InvalidInputError(f"blur_sigma_m must be finite and >= 0, got {blur_sigma_m}")
    blurred = []
    for poses in hypotheses_world:
        poses = np.array(poses, dtype=np.float64).reshape(-1, 3)
        poses[:, :2] += rng.normal(0.0, blur_sigma_m, size=(len(poses), 2))
        blurred.append(poses)
    return best_of_k_errors(blurred, truth_world)


@dataclass(frozen=True)
class ExcursionCauses:
    """The frames whose estimate is missing or further than ``tolerance_m`` from the
    truth (position only), by what the frame's hypotheses held: where the error came
    from. ``no_estimate``: the filter had not started; ``no_hypotheses``: none came
    (dead reckoning: a gap, or streets beyond the map); ``hypotheses_off``: every
    hypothesis was as far off (the map or the PnP wrong, nothing a filter could pick);
    ``filter_off``: one was within the tolerance and the filter was elsewhere."""

    tolerance_m: float
    frames: int
    off: int
    no_estimate: int
    no_hypotheses: int
    hypotheses_off: int
    filter_off: int

    def to_dict(self) -> dict:
        return asdict(self)

    def text(self) -> str:
        """One line: how many frames were off, and why."""
        return (
            f"{self.off} of {self.frames} frames beyond {self.tolerance_m:g} m: "
            f"{self.no_estimate} before the start, {self.no_hypotheses} without hypotheses, "
            f"{self.hypotheses_off} with every hypothesis beyond it, {self.filter_off} with "
            "one within it but the filter elsewhere"
        )


def excursion_causes(
    estimate_world: np.ndarray,
    truth_world: np.ndarray,
    hypotheses_world: list[np.ndarray],
    tolerance_m: float = 0.25,
) -> ExcursionCauses:
    """Sort the frames whose estimate (N, 3; NaN rows: no estimate) is beyond
    ``tolerance_m`` of the truth (N, 3) by their hypotheses ((H, 3) per frame)."""
    if not tolerance_m > 0:
        raise InvalidInputError(f"tolerance_m must be > 0, got {tolerance_m}")
    est = np.asarray(estimate_world, dtype=np.float64).reshape(-1, 3)
    truth = np.asarray(truth_world, dtype=np.float64)
    if est.shape != truth.shape:
        raise InvalidInputError(f"estimates {est.shape} and truth {truth.shape} differ")
    best = best_of_k_errors(hypotheses_world, truth)
    error = np.linalg.norm(est[:, :2] - truth[:, :2], axis=1)
    missing = ~np.isfinite(error)
    off = missing | (error > tolerance_m)
    with_estimate_off = off & ~missing
    none = ~np.isfinite(best)
    return ExcursionCauses(
        tolerance_m=float(tolerance_m),
        frames=len(truth),
        off=int(off.sum()),
        no_estimate=int(missing.sum()),
        no_hypotheses=int((with_estimate_off & none).sum()),
        hypotheses_off=int((with_estimate_off & ~none & (best > tolerance_m)).sum()),
        filter_off=int((with_estimate_off & ~none & (best <= tolerance_m)).sum()),
    )


def time_to_recover(
    position_error_m: np.ndarray,
    timestamps_s: np.ndarray,
    since: int,
    tolerance_m: float = 0.5,
    hold_frames: int = 10,
) -> float:
    """Seconds from frame ``since`` until the error (N,) falls within ``tolerance_m`` and
    stays there for ``hold_frames`` frames (or to the end of the run); inf if it never
    does. NaN errors (no estimate) count as outside."""
    err = np.nan_to_num(np.asarray(position_error_m, dtype=np.float64), nan=np.inf)
    ok = err <= tolerance_m
    for i in range(since, len(err)):
        if ok[i : i + hold_frames].all():
            return float(timestamps_s[i] - timestamps_s[since])
    return math.inf


def truth_in_map_frame(
    query_true_world: np.ndarray,
    map_true_world: np.ndarray,
    map_written_world: np.ndarray,
) -> np.ndarray:
    """Where a localizer that is exact relative to the map puts each query frame (N, 3):
    the query's true planar pose (N, 3) moved by the recorded pose error (written minus
    true, heading wrapped) of the map frame nearest to it (true positions; map poses
    (M, 3) each). A map whose ground truth is off by a slowly varying error carries its
    entries' hypotheses with it; the distance from this pose to the query's written
    truth is what the recording errors alone cost (the nearest entry stands for the few
    a frame is localized against)."""
    q = np.asarray(query_true_world, dtype=np.float64)
    true_m = np.asarray(map_true_world, dtype=np.float64)
    written_m = np.asarray(map_written_world, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 3 or true_m.shape != written_m.shape or true_m.ndim != 2:
        raise InvalidInputError(
            f"need query poses (N, 3) and matching map poses (M, 3), got {q.shape}, "
            f"{true_m.shape} and {written_m.shape}"
        )
    if not len(true_m):
        raise InvalidInputError("need at least one map pose")
    d = q[:, None, :2] - true_m[None, :, :2]
    nearest = np.argmin(np.einsum("nmk,nmk->nm", d, d), axis=1)
    error = written_m[nearest] - true_m[nearest]
    out = q + error
    out[:, 2] = wrap_angle(q[:, 2] + wrap_angle(error[:, 2]))
    return out

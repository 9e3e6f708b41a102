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

"""A driven trajectory (``monoloc drive``'s TUM or KITTI file) written as kapture."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InputFileError
from monoloc.core.formats import kitti, tum
from monoloc.core.geometry import kitti_to_zup


def read_driven_trajectory(path: Path, times: Path | None = None):
    """(timestamps_s (N,), T_world_from_cam (N, 4, 4) z-up) from a TUM file, or from a
    KITTI file (``*.kitti.txt``: KITTI's world, converted) with its ``times`` file."""
    path = Path(path)
    if path.name.endswith(".kitti.txt") or times is not None:
        if times is None:
            raise InputFileError(path, "a KITTI trajectory has no timestamps: give --times")
        poses = kitti_to_zup(kitti.read_poses(path))
        stamps = kitti.read_times(times)
        if len(stamps) != len(poses):
            raise InputFileError(times, f"{len(stamps)} timestamps for {len(poses)} poses")
        return stamps, poses
    trajectory = tum.read_trajectory(path)
    return trajectory.timestamps_s, trajectory.T_world_from_cam


def export_trajectory(
    path: Path, out_dir: Path, *, times: Path | None = None, camera: CameraIntrinsics | None = None
) -> int:
    """Write the trajectory file as a kapture dataset; returns the number of poses."""
    from monoloc.server.formats.kapture_io import write_kapture_trajectory

    stamps, poses = read_driven_trajectory(path, times)
    marker = {
        "written_by": "monoloc",
        "up": "z",
        "world": "monoloc z-up world, metres",
        "trajectory": str(path),
    }
    write_kapture_trajectory(np.asarray(stamps), poses, out_dir, camera=camera, marker=marker)
    return len(stamps)

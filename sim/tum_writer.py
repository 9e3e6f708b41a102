"""The sim's writers of the TUM RGB-D layout, one folder per run; the files' contents are
``monoloc.core.formats.tum`` (file lists, trajectories, depth encoding, camera.json) and
``monoloc.core.formats.vehicle``; here the images (OpenCV) and dataset.json::

    <root>/<run>/rgb/<t>.png        8-bit colour PNG (the sim renders monochrome: three
                                    identical channels)
    <root>/<run>/depth/<t>.png      uint16 z-depth * 5000 (0.2 mm), 0 = no depth,
                                    registered to the rgb image
    <root>/<run>/rgb.txt            "timestamp filename" after TUM's three '#' lines
    <root>/<run>/depth.txt          same for depth
    <root>/<run>/groundtruth.txt    "timestamp tx ty tz qx qy qz qw": T_world_from_cam
                                    (OpenCV camera axes) at the motion capture's stamps
    <root>/<run>/vehicle.txt        "t speed_mps yaw_rate_radps" at the rgb stamps
    <root>/<run>/camera.json        fx, fy, cx, cy, width, height, depth_scale_per_m
    <root>/dataset.json             what each run is (see monoloc.sim.indoor.generate)

Timestamps are seconds on one clock (as TUM's, Unix-like), written with 6 decimals;
an image's file name is its stamp exactly as listed.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.core.formats import tum, vehicle
from monoloc.core.geometry import R_from_quaternion_xyzw, quaternion_xyzw_from_R


def write_file_list(path: Path, what: str, source: str, stamps_s, rel_paths) -> None:
    """rgb.txt / depth.txt with TUM's header (``what``: 'color images' | 'depth maps')."""
    with open(path, "w") as handle:
        tum.write_file_list(
            handle, stamps_s, rel_paths, comments=[what, f"file: '{source}'", "timestamp filename"]
        )


def write_ground_truth(path: Path, source: str, stamps_s, T_world_from_cam) -> None:
    """groundtruth.txt: one ``t tx ty tz qx qy qz qw`` line per (4, 4) pose."""
    header = ["ground truth trajectory", f"file: '{source}'", "timestamp tx ty tz qx qy qz qw"]
    with open(path, "w") as handle:
        tum.write_trajectory(
            handle,
            stamps_s,
            T_world_from_cam,
            comments=header,
            position_decimals=6,
            quaternion_decimals=7,
        )


def pose_at(stamps_s: np.ndarray, T_world_from_cam: np.ndarray, t_s: float) -> np.ndarray:
    """(4, 4) pose at ``t_s`` interpolated between the bracketing samples (position
    linearly, rotation by slerp); raises outside the samples."""
    k = int(np.searchsorted(stamps_s, t_s, side="right"))
    if k == 0 or (k == len(stamps_s) and t_s > stamps_s[-1]):
        raise InvalidInputError(f"time {t_s:.6f} is outside the ground truth")
    if k == len(stamps_s):
        return T_world_from_cam[-1].copy()
    a = (t_s - stamps_s[k - 1]) / (stamps_s[k] - stamps_s[k - 1])
    q0 = quaternion_xyzw_from_R(T_world_from_cam[k - 1, :3, :3])
    q1 = quaternion_xyzw_from_R(T_world_from_cam[k, :3, :3])
    if np.dot(q0, q1) < 0:
        q1 = -q1
    angle = np.arccos(np.clip(np.dot(q0, q1), -1.0, 1.0))
    if angle < 1e-9:
        q = q0
    else:
        q = (np.sin((1 - a) * angle) * q0 + np.sin(a * angle) * q1) / np.sin(angle)
    T = np.eye(4)
    T[:3, :3] = R_from_quaternion_xyzw(q)
    T[:3, 3] = (1 - a) * T_world_from_cam[k - 1, :3, 3] + a * T_world_from_cam[k, :3, 3]
    return T


def write_vehicle(path: Path, stamps_s, speed_mps, yaw_rate_radps) -> None:
    """vehicle.txt: ``t speed_mps yaw_rate_radps`` per rgb frame."""
    with open(path, "w") as handle:
        vehicle.write_vehicle(handle, stamps_s, speed_mps, yaw_rate_radps)


def write_depth(path: Path, depth_m: np.ndarray) -> None:
    import cv2

    if not cv2.imwrite(str(path), tum.encode_depth(depth_m), [cv2.IMWRITE_PNG_COMPRESSION, 3]):
        raise InvalidInputError(f"could not write {path}")


def read_depth(path: Path) -> np.ndarray:
    """Depth PNG -> (H, W) float32 metres, 0 where there is no depth."""
    import cv2

    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
        raise InvalidInputError(f"{path}: not a 16-bit single-channel depth PNG")
    return raw.astype(np.float32) / tum.DEPTH_SCALE_PER_M


def write_rgb(path: Path, image: np.ndarray) -> None:
    """(H, W) uint8 gray -> 3-channel PNG (identical channels; OpenCV's gray conversion
    gives the rendered image back exactly)."""
    import cv2

    bgr = np.repeat(image[:, :, None], 3, axis=2) if image.ndim == 2 else image
    if not cv2.imwrite(str(path), bgr, [cv2.IMWRITE_PNG_COMPRESSION, 3]):
        raise InvalidInputError(f"could not write {path}")


def write_dataset_json(root: Path, info: dict) -> None:
    (Path(root) / "dataset.json").write_text(json.dumps(info, indent=2) + "\n")

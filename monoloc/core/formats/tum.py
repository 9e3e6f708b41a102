"""TUM RGB-D: its text files (the format evo and TUM's tools read) and its run layout,
read and written here (the sim writes it, the server ingests it, the vehicle replays it).

``groundtruth.txt`` (any TUM trajectory)  ``timestamp tx ty tz qx qy qz qw`` per line:
    T_world_from_cam, position in metres, unit quaternion (x, y, z, w).
``rgb.txt`` / ``depth.txt`` (file lists)  ``timestamp filename`` per line, the filename
    relative to the list's folder.

Both skip blank lines and '#' comments. Timestamps are seconds, written with 6 decimals
(``stamp_text``); TUM names an image file after its stamp as listed.

Run layout::

    <root>/rgb.txt           "timestamp path" per line ('#' comments), paths relative to root
    <root>/depth.txt         same, 16-bit depth PNGs registered to the colour image
                             (DEPTH_SCALE_PER_M raw units per metre, 0: no depth)
    <root>/groundtruth.txt   "timestamp tx ty tz qx qy qz qw": T_world_from_cam
    <root>/<intrinsics>.json optional camera description (``read_camera_json``)
    <root>/vehicle.txt       monoloc's: speed and yaw rate (core.formats.vehicle)

:func:`read_run` opens a run as a mapping run: see its docstring for the association of
colour and depth images, the ground truth at a frame's stamp and the intrinsics.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import numpy as np

from monoloc.core.camera import CameraIntrinsics, LensDistortion
from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.formats._text import Source, data_lines, finite_numbers, number_rows, read_lines
from monoloc.core.formats.png import png_size
from monoloc.core.geometry import R_from_quaternion_xyzw, kitti_to_zup, quaternion_xyzw_from_R

QUATERNION_NORM_TOL = 0.01  # TUM's files give 4 decimals
DEPTH_SCALE_PER_M = 5000.0  # TUM's depth PNGs: 0.2 mm per unit
INTRINSICS_FILES = ("intrinsics.json", "camera.json", "calib.json")
# TUM RGB-D's published (ROS default and calibrated) colour camera pinhole parameters.
TUM_CAMERAS = {
    "default": (525.0, 525.0, 319.5, 239.5),
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}


def stamp_text(t_s: float) -> str:
    """A timestamp as TUM files write it (and name images after it): 6 decimals."""
    return f"{t_s:.6f}"


@dataclass(frozen=True)
class TumTrajectory:
    """Poses as read: timestamps_s (N,), position_world_m (N, 3) and q_world_from_cam_xyzw
    (N, 4), the quaternion as written (unit within QUATERNION_NORM_TOL)."""

    timestamps_s: np.ndarray
    position_world_m: np.ndarray = field(repr=False)
    q_world_from_cam_xyzw: np.ndarray = field(repr=False)

    def __len__(self) -> int:
        return len(self.timestamps_s)

    @property
    def T_world_from_cam(self) -> np.ndarray:
        """(N, 4, 4) float64 poses."""
        T = np.tile(np.eye(4), (len(self), 1, 1))
        for i, (position, q) in enumerate(
            zip(self.position_world_m, self.q_world_from_cam_xyzw, strict=True)
        ):
            T[i, :3, :3] = R_from_quaternion_xyzw(q)
            T[i, :3, 3] = position
        return T


def read_trajectory(source: Source) -> TumTrajectory:
    """A TUM trajectory (groundtruth.txt) -> TumTrajectory, in file order; at least one
    pose, every number finite, every quaternion of norm 1 (within 0.01)."""
    path, rows, numbers = number_rows(source, 8, "ground-truth pose")
    if len(rows) == 0:
        raise InputFileError(path, "no ground-truth poses")
    norms = np.linalg.norm(rows[:, 4:8], axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > QUATERNION_NORM_TOL)
    if len(bad):
        raise InputFileError(
            path, f"quaternion norm {norms[bad[0]]:.4f} is not 1 (qx qy qz qw)", numbers[bad[0]]
        )
    return TumTrajectory(rows[:, 0], rows[:, 1:4], rows[:, 4:8])


def write_trajectory(
    handle: TextIO,
    timestamps_s: np.ndarray,
    T_world_from_cam: np.ndarray,
    *,
    comments: Sequence[str] = (),
    position_decimals: int = 9,
    quaternion_decimals: int = 9,
) -> None:
    """``# comment`` lines, then ``t tx ty tz qx qy qz qw`` per (4, 4) pose (qw >= 0)."""
    if len(timestamps_s) != len(T_world_from_cam):
        raise InvalidInputError("timestamps and poses differ in length")
    for comment in comments:
        handle.write(f"# {comment}\n")
    for t, T in zip(timestamps_s, T_world_from_cam, strict=True):
        q = quaternion_xyzw_from_R(T[:3, :3])
        position = " ".join(f"{v:.{position_decimals}f}" for v in T[:3, 3])
        rotation = " ".join(f"{v:.{quaternion_decimals}f}" for v in q)
        handle.write(f"{stamp_text(t)} {position} {rotation}\n")


def read_file_list(source: Source, root: Path | None = None) -> tuple[np.ndarray, list[str]]:
    """rgb.txt / depth.txt -> (timestamps_s (N,), filenames as listed); at least one.
    With ``root``, every listed file must exist under it (the error names the line)."""
    path, lines = read_lines(source, "file list")
    stamps, names = [], []
    for number, fields in data_lines(lines):
        if len(fields) != 2:
            raise InputFileError(
                path, f"expected 'timestamp filename', got {len(fields)} fields", number
            )
        stamps.extend(finite_numbers(path, number, fields[:1], "timestamp"))
        if root is not None and not (Path(root) / fields[1]).is_file():
            raise InputFileError(path, f"lists {fields[1]}, which does not exist", number)
        names.append(fields[1])
    if not names:
        raise InputFileError(path, "lists no files")
    return np.asarray(stamps, dtype=np.float64), names


def write_file_list(
    handle: TextIO, timestamps_s: np.ndarray, names: Sequence[str], *, comments: Sequence[str] = ()
) -> None:
    """``# comment`` lines, then ``timestamp filename`` per file."""
    if len(timestamps_s) != len(names):
        raise InvalidInputError("timestamps and filenames differ in length")
    for comment in comments:
        handle.write(f"# {comment}\n")
    for t, name in zip(timestamps_s, names, strict=True):
        handle.write(f"{stamp_text(t)} {name}\n")


# ---- the run layout: depth images, camera JSON, association, ground truth, runs -------


def encode_depth(depth_m: np.ndarray) -> np.ndarray:
    """(H, W) metres (0, negative or non-finite: none) -> uint16 at DEPTH_SCALE_PER_M per
    metre, a depth PNG's pixels; depths beyond 13.107 m cannot be encoded and are 0."""
    d = np.where(np.isfinite(depth_m) & (depth_m > 0), depth_m * DEPTH_SCALE_PER_M + 0.5, 0.0)
    return np.where(d < 65535.5, d, 0.0).astype(np.uint16)


def write_camera_json(path: str | os.PathLike, intrinsics: CameraIntrinsics, extra: dict) -> None:
    """camera.json: fx, fy, cx, cy, width, height, depth_scale_per_m (DEPTH_SCALE_PER_M)
    and the ``extra`` keys (``world_frame`` is read back; ``T_vehicle_from_cam``, where
    the camera sits, by the vehicle's replay; others are for people); and camera.yaml
    beside it, the camera and its mounting in ROS's calibration layout
    (``monoloc.core.formats.camera_yaml``)."""
    from monoloc.core.formats.camera_yaml import CAMERA_YAML, write_camera_yaml

    k = intrinsics
    info = {
        "fx": k.fx,
        "fy": k.fy,
        "cx": k.cx,
        "cy": k.cy,
        "width": k.width_px,
        "height": k.height_px,
        "depth_scale_per_m": DEPTH_SCALE_PER_M,
        **extra,
    }
    Path(path).write_text(json.dumps(info, indent=2) + "\n")
    T_vehicle_from_cam = extra.get("T_vehicle_from_cam")
    write_camera_yaml(Path(path).with_name(CAMERA_YAML), intrinsics, T_vehicle_from_cam)


def read_camera_json(root: str | os.PathLike) -> tuple[Path | None, dict]:
    """(path, contents) of the first of INTRINSICS_FILES in a run folder, keys of a nested
    ``camera`` / ``intrinsics`` object merged in; (None, {}) when there is none."""
    for name in INTRINSICS_FILES:
        path = Path(root) / name
        if path.is_file():
            try:
                data = json.loads(path.read_text())
            except (OSError, ValueError) as exc:
                raise InputFileError(path, f"cannot read camera JSON: {exc}") from exc
            if not isinstance(data, dict):
                raise InputFileError(path, "camera JSON must be an object")
            for key in ("camera", "intrinsics"):
                if isinstance(data.get(key), dict):
                    data = {**data, **data[key]}
            return path, data
    return None, {}


@dataclass(frozen=True)
class TumFrame:
    """One associated frame; ``index`` is its position in rgb.txt (0-based)."""

    index: int
    timestamp_s: float
    image_path: Path
    depth_path: Path
    depth_timestamp_s: float
    T_world_from_cam: np.ndarray = field(repr=False)


@dataclass(frozen=True)
class TumRun:
    root: Path
    intrinsics: CameraIntrinsics
    depth_scale_per_m: float
    frames: list[TumFrame] = field(repr=False)
    read_skips: dict[str, int] = field(default_factory=dict)
    format: str = "tum"

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    @property
    def name(self) -> str:
        return str(self.root)


def read_listed_files(path: str | os.PathLike) -> tuple[np.ndarray, list[Path]]:
    """rgb.txt / depth.txt -> (timestamps (N,), absolute paths); every file must exist."""
    path = Path(path)
    stamps, names = read_file_list(path, root=path.parent)
    return stamps, [path.parent / name for name in names]


def associate(
    stamps_a: np.ndarray, stamps_b: np.ndarray, max_difference_s: float = 0.02
) -> list[tuple[int, int]]:
    """Greedy one-to-one association by increasing |a - b| < max_difference_s (TUM's
    ``associate.py``). Returns (index_a, index_b) pairs sorted by index_a."""
    a, b = np.asarray(stamps_a, dtype=np.float64), np.asarray(stamps_b, dtype=np.float64)
    order_b = np.argsort(b, kind="stable")
    sorted_b = b[order_b]
    lo = np.searchsorted(sorted_b, a - max_difference_s, side="left")
    hi = np.searchsorted(sorted_b, a + max_difference_s, side="right")
    candidates = []
    for i in range(len(a)):
        for j in range(lo[i], hi[i]):
            diff = abs(a[i] - sorted_b[j])
            if diff < max_difference_s:
                candidates.append((diff, i, int(order_b[j])))
    candidates.sort()
    used_a, used_b, pairs = set(), set(), []
    for _, i, j in candidates:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    return sorted(pairs)


def _slerp(q0: np.ndarray, q1: np.ndarray, alpha: float) -> np.ndarray:
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + alpha * (q1 - q0)
    else:
        theta = np.arccos(dot)
        q = (np.sin((1 - alpha) * theta) * q0 + np.sin(alpha * theta) * q1) / np.sin(theta)
    return q / np.linalg.norm(q)


def ground_truth_at(
    gt: np.ndarray, t: float, max_difference_s: float = 0.02, gt_max_gap_s: float = 0.1
) -> np.ndarray | None:
    """T_world_from_cam (4, 4) at time t from sorted rows (t tx ty tz qx qy qz qw), or None:
    interpolated (translation linearly, rotation by slerp) between the two rows bracketing
    t when they are at most ``gt_max_gap_s`` apart, else the nearest row within
    ``max_difference_s``."""
    times = gt[:, 0]
    k = int(np.searchsorted(times, t, side="left"))
    row = None
    if k < len(times) and times[k] == t:
        row = gt[k, 1:]
    elif 0 < k < len(times) and times[k] - times[k - 1] <= gt_max_gap_s:
        alpha = (t - times[k - 1]) / (times[k] - times[k - 1])
        position = (1 - alpha) * gt[k - 1, 1:4] + alpha * gt[k, 1:4]
        row = np.concatenate([position, _slerp(gt[k - 1, 4:], gt[k, 4:], alpha)])
    else:
        near = [j for j in (k - 1, k) if 0 <= j < len(times)]
        best = min(near, key=lambda j: abs(times[j] - t))
        if abs(times[best] - t) <= max_difference_s:
            row = gt[best, 1:]
    if row is None:
        return None
    T = np.eye(4)
    T[:3, :3] = R_from_quaternion_xyzw(row[3:7])
    T[:3, 3] = row[:3]
    return T


def read_ground_truth(path: str | os.PathLike) -> np.ndarray:
    """groundtruth.txt -> (N, 8) rows (t tx ty tz qx qy qz qw) sorted by time, quaternions
    normalised."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "ground-truth file is missing")
    gt = read_trajectory(path)
    q = gt.q_world_from_cam_xyzw
    rows = np.column_stack(
        [gt.timestamps_s, gt.position_world_m, q / np.linalg.norm(q, axis=1)[:, None]]
    )
    return rows[np.argsort(rows[:, 0], kind="stable")]


def _intrinsics(root, intrinsics, camera, json_path, data, first_image) -> CameraIntrinsics:
    if intrinsics is not None:
        return intrinsics
    if camera is not None:
        if camera not in TUM_CAMERAS:
            raise InvalidInputError(f"unknown TUM camera {camera!r}; one of {sorted(TUM_CAMERAS)}")
        return CameraIntrinsics(*TUM_CAMERAS[camera], 640, 480)
    if json_path is None:
        raise InvalidInputError(
            f"{root}: no camera intrinsics: add one of {INTRINSICS_FILES}, or give "
            "--camera freiburg1|freiburg2|freiburg3|default or --fx/--fy/--cx/--cy"
        )
    try:
        fx, fy, cx, cy = (float(data[k]) for k in ("fx", "fy", "cx", "cy"))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputFileError(json_path, f"needs numeric fx, fy, cx, cy ({exc})") from exc
    width = data.get("width_px", data.get("width"))
    height = data.get("height_px", data.get("height"))
    if width is None or height is None:
        width, height = png_size(first_image)
    try:
        lens = LensDistortion.parse(
            data.get("distortion_model"), data.get("D", data.get("distortion"))
        )
        return CameraIntrinsics(fx, fy, cx, cy, int(width), int(height), lens)
    except (InvalidInputError, TypeError, ValueError) as exc:
        raise InputFileError(json_path, str(exc)) from exc


def read_run_camera(
    root: str | os.PathLike, first_image: str | os.PathLike
) -> CameraIntrinsics | None:
    """The run's own camera from its camera JSON (``read_camera_json``; its size, else the
    first image's), or None when the run has none (a vehicle must then say which)."""
    json_path, data = read_camera_json(root)
    if json_path is None:
        return None
    return _intrinsics(root, None, None, json_path, data, first_image)


def read_run(
    root: str | os.PathLike,
    *,
    intrinsics: CameraIntrinsics | None = None,
    camera: str | None = None,
    max_difference_s: float = 0.02,
    gt_max_gap_s: float = 0.1,
    frames: slice | None = None,
) -> TumRun:
    """Open and validate a TUM RGB-D run as a mapping run.

    Association (as TUM's ``associate.py``): every (rgb, depth) pair closer than
    ``max_difference_s`` is a candidate; candidates are taken greedily by increasing time
    difference, each timestamp used at most once. Ground truth at an rgb stamp:
    :func:`ground_truth_at`; a frame without is dropped (``read_skips['no_ground_truth']``;
    rgb frames without a depth partner are counted as ``no_depth``: TUM's recordings
    routinely start the motion capture after the camera, so these are reported, not
    errors).

    Intrinsics, first match wins: ``intrinsics``; a named TUM camera (``camera``: a key of
    TUM_CAMERAS, 640x480); the run's camera JSON (``read_camera_json``) with fx, fy, cx, cy
    and optionally width/height (or width_px/height_px; else the first image's size),
    ``depth_scale`` (raw units per metre, default DEPTH_SCALE_PER_M) and ``world_frame``.
    The ground-truth world is taken to be z-up (monoloc's convention) unless
    ``world_frame`` is ``"kitti"`` or ``"camera"`` (x right, y down, z forward), converted
    with ``kitti_to_zup``. ``frames`` selects associated frames with Python slice
    semantics.
    """
    root = Path(root).expanduser().resolve()
    if not root.is_dir():
        raise InputFileError(root, "TUM run path is not a directory")
    for name in ("rgb.txt", "depth.txt"):
        if not (root / name).is_file():
            raise InputFileError(root / name, "file list is missing")
    rgb_t, rgb_files = read_listed_files(root / "rgb.txt")
    depth_t, depth_files = read_listed_files(root / "depth.txt")
    gt = read_ground_truth(root / "groundtruth.txt")
    json_path, data = read_camera_json(root)
    camera_model = _intrinsics(root, intrinsics, camera, json_path, data, rgb_files[0])
    if camera_model.distortion is not None:
        raise InputFileError(
            json_path or root,
            f"the mapping camera has {camera_model.distortion.model} lens distortion; maps "
            "are built from rectified images (a query may be distorted)",
        )
    scale = float(data.get("depth_scale", data.get("depth_scale_per_m", DEPTH_SCALE_PER_M)))
    if not np.isfinite(scale) or scale <= 0:
        raise InputFileError(json_path or root, f"depth_scale must be positive, got {scale}")
    world = str(data.get("world_frame", "z-up")).lower()
    if world not in ("z-up", "zup", "kitti", "camera"):
        raise InputFileError(json_path or root, f"unknown world_frame {world!r}")
    pairs = associate(rgb_t, depth_t, max_difference_s)
    skips = {"no_depth": len(rgb_t) - len(pairs), "no_ground_truth": 0}
    out: list[TumFrame] = []
    for i, j in pairs:
        T = ground_truth_at(gt, float(rgb_t[i]), max_difference_s, gt_max_gap_s)
        if T is None:
            skips["no_ground_truth"] += 1
            continue
        if world in ("kitti", "camera"):
            T = kitti_to_zup(T)
        out.append(TumFrame(i, float(rgb_t[i]), rgb_files[i], depth_files[j], float(depth_t[j]), T))
    if frames is not None:
        out = out[frames]
    return TumRun(
        root=root,
        intrinsics=camera_model,
        depth_scale_per_m=scale,
        frames=out,
        read_skips={k: v for k, v in skips.items() if v},
    )

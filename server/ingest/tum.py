"""Reader of TUM RGB-D runs (and of the sim's indoor output, which has the same layout).

Layout (the text files' formats are ``monoloc.core.formats.tum``)::

    <root>/rgb.txt           "timestamp path" per line ('#' comments), paths relative to root
    <root>/depth.txt         same, 16-bit depth PNGs registered to the colour image
    <root>/groundtruth.txt   "timestamp tx ty tz qx qy qz qw": T_world_from_cam
    <root>/<intrinsics>.json optional camera description (see below)

Association (as TUM's ``associate.py``): every (rgb, depth) pair closer than
``max_difference_s`` (0.02 s) is a candidate; candidates are taken greedily by
increasing time difference, each timestamp used at most once.

Ground truth at an rgb timestamp t: interpolated (translation linearly, rotation by
slerp) between the two ground-truth samples bracketing t when they are at most
``gt_max_gap_s`` (0.1 s) apart; otherwise the nearest sample if within
``max_difference_s``; otherwise the frame has no ground truth and is dropped (counted
in ``read_skips['no_ground_truth']``; rgb frames without a depth partner are counted as
``no_depth``). TUM's recordings routinely start the motion capture after the camera, so
these are reported, not errors.

Intrinsics, first match wins: the ``intrinsics`` argument; a named TUM camera
(``freiburg1``/``freiburg2``/``freiburg3``/``default``: TUM's published pinhole values,
640x480); the first of ``intrinsics.json``, ``camera.json``, ``calib.json`` in the run
folder with keys fx, fy, cx, cy and optionally width/height (or width_px/height_px; else
the first image's size), ``depth_scale`` (raw units per metre, default 5000) and
``world_frame``. The ground-truth world is taken to be z-up (monoloc's convention)
unless ``world_frame`` is ``"kitti"`` or ``"camera"`` (x right, y down, z forward),
which is converted with ``monoloc.core.geometry.kitti_to_zup``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.formats import tum as tum_format
from monoloc.core.geometry import R_from_quaternion_xyzw, kitti_to_zup
from monoloc.server.ingest.common import (
    LoadedFrame,
    decode_depth,
    decode_gray,
    png_size,
    read_bytes,
)

TUM_DEPTH_SCALE_PER_M = 5000.0
INTRINSICS_FILES = ("intrinsics.json", "camera.json", "calib.json")
# TUM RGB-D's published (ROS default and calibrated) colour camera pinhole parameters.
TUM_CAMERAS = {
    "default": (525.0, 525.0, 319.5, 239.5),
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}


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

    def load(self, frame: TumFrame) -> LoadedFrame:
        """Read the frame's colour and depth images (thread-safe; no database access)."""
        from monoloc.server.entry_builder import DepthSource

        data = read_bytes(frame.image_path, "image")
        image = decode_gray(data, frame.image_path)
        depth = decode_depth(read_bytes(frame.depth_path, "depth image"), frame.depth_path)
        return LoadedFrame(data, image, DepthSource(depth, self.depth_scale_per_m))


def read_file_list(path: Path) -> tuple[np.ndarray, list[Path]]:
    """rgb.txt / depth.txt -> (timestamps (N,), absolute paths); every file must exist."""
    path = Path(path)
    stamps, names = tum_format.read_file_list(path, root=path.parent)
    return stamps, [path.parent / name for name in names]


def associate(
    stamps_a: np.ndarray, stamps_b: np.ndarray, max_difference_s: float = 0.02
) -> list[tuple[int, int]]:
    """Greedy one-to-one association by increasing |a - b| < max_difference_s (TUM's rule).

    Returns (index_a, index_b) pairs sorted by index_a.
    """
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
    """T_world_from_cam (4, 4) at time t from sorted rows (t tx ty tz qx qy qz qw), or None
    (interpolated if bracketed within ``gt_max_gap_s``, else nearest within
    ``max_difference_s``)."""
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


def read_ground_truth(path: Path) -> np.ndarray:
    """groundtruth.txt -> (N, 8) rows (t tx ty tz qx qy qz qw) sorted by time, quaternions
    normalised."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "ground-truth file is missing")
    gt = tum_format.read_trajectory(path)
    q = gt.q_world_from_cam_xyzw
    rows = np.column_stack(
        [gt.timestamps_s, gt.position_world_m, q / np.linalg.norm(q, axis=1)[:, None]]
    )
    return rows[np.argsort(rows[:, 0], kind="stable")]


def _camera_json(root: Path) -> tuple[Path | None, dict]:
    for name in INTRINSICS_FILES:
        path = root / name
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
        return CameraIntrinsics(fx, fy, cx, cy, int(width), int(height))
    except InvalidInputError as exc:
        raise InputFileError(json_path, str(exc)) from exc


def read_tum_run(
    root: Path,
    *,
    intrinsics: CameraIntrinsics | None = None,
    camera: str | None = None,
    max_difference_s: float = 0.02,
    gt_max_gap_s: float = 0.1,
    frames: slice | None = None,
) -> TumRun:
    """Open and validate a TUM RGB-D run (see the module docstring). ``frames`` selects
    associated frames with Python slice semantics."""
    root = Path(root).expanduser().resolve()
    if not root.is_dir():
        raise InputFileError(root, "TUM run path is not a directory")
    for name in ("rgb.txt", "depth.txt"):
        if not (root / name).is_file():
            raise InputFileError(root / name, "file list is missing")
    rgb_t, rgb_files = read_file_list(root / "rgb.txt")
    depth_t, depth_files = read_file_list(root / "depth.txt")
    gt = read_ground_truth(root / "groundtruth.txt")
    json_path, data = _camera_json(root)
    camera_model = _intrinsics(root, intrinsics, camera, json_path, data, rgb_files[0])
    scale = float(data.get("depth_scale", data.get("depth_scale_per_m", TUM_DEPTH_SCALE_PER_M)))
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

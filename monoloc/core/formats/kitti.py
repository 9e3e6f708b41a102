"""KITTI odometry: its text files and its layout, read and written here (the sim writes
it, the server ingests it, the vehicle replays it).

Layout (the real dataset's)::

    <root>/sequences/NN/calib.txt         "P0: 12 numbers" ... "Tr: 12 numbers"
    <root>/sequences/NN/times.txt         one timestamp (s) per frame
    <root>/sequences/NN/image_0/%06d.png  grayscale left camera
    <root>/sequences/NN/image_1/%06d.png  grayscale right camera (depth_from="stereo")
    <root>/sequences/NN/velodyne/%06d.bin float32 (x, y, z, reflectance), LiDAR frame
    <root>/sequences/NN/vehicle.txt       monoloc's: speed and yaw rate (core.formats.vehicle)
    <root>/poses/NN.txt                   3x4 T_kittiworld_from_cam0 per line, row-major

``poses/NN.txt``  one pose per line: 12 numbers, the top 3x4 of T_kittiworld_from_cam0,
                  row-major. KITTI's world is its first camera frame (x right, y down,
                  z forward); ``monoloc.core.geometry.kitti_to_zup`` converts it.
``times.txt``     one timestamp (s) per frame.
``calib.txt``     ``NAME: 12 numbers`` lines: ``P0`` .. ``P3`` (3x4, the rectified camera-0
                  frame to camera i's pixels) and ``Tr`` (top 3x4 of T_cam0_from_lidar).
                  Other names are ignored.

A sequence is named by the dataset root and ``NN`` (optional when there is only one), or
by its folder; then the poses are ``<seq>/poses.txt`` if present, else
``<seq>/../../poses/NN.txt`` (:func:`resolve_sequence`). :func:`read_sequence` opens one
as a mapping run and validates everything but the image and scan contents before
anything is read: see its docstring.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.formats._text import Source, finite_numbers, number_rows, read_lines
from monoloc.core.formats.png import png_size
from monoloc.core.geometry import check_rigid, kitti_to_zup

RIGID_TOL = 1e-3  # the files hold 9 to 12 significant digits
_PROJECTION_RE = re.compile(r"^P(\d+)$")
RECTIFIED_TOL = 1e-6  # relative: P1's camera matrix must equal P0's
KITTI_STEREO_BASELINE_M = 0.5371657
KITTI_COLOUR_OFFSET_M = -0.0598  # camera 2 sits ~6 cm left of camera 0 in KITTI
LIDAR_POINT_BYTES = 16  # float32 x, y, z, reflectance
DEPTH_SOURCES = ("lidar", "stereo", "none")


def _rigid_4x4(top_3x4: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :] = top_3x4
    return T


def read_poses(source: Source) -> np.ndarray:
    """poses/NN.txt -> (N, 4, 4) float64 T_kittiworld_from_cam; every pose finite and
    rigid, at least one."""
    path, rows, numbers = number_rows(source, 12, "pose")
    if len(rows) == 0:
        raise InputFileError(path, "no poses")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    for pose, number in zip(poses, numbers, strict=True):
        try:
            check_rigid(pose, "pose", tol=RIGID_TOL)
        except InvalidInputError as exc:
            raise InputFileError(
                path, "pose is not rigid (rotation not orthonormal)", number
            ) from exc
    return poses


def write_poses(handle: TextIO, T_kittiworld_from_cam: np.ndarray) -> None:
    """(N, 4, 4) or (N, 3, 4) poses -> one line of 12 numbers (top 3x4, row-major) each."""
    for T in np.asarray(T_kittiworld_from_cam, dtype=np.float64):
        handle.write(" ".join(f"{v:.9e}" for v in T[:3, :4].reshape(-1)) + "\n")


def read_times(source: Source) -> np.ndarray:
    """times.txt -> (N,) float64 timestamps_s, at least one."""
    path, rows, _ = number_rows(source, 1, "timestamp")
    if len(rows) == 0:
        raise InputFileError(path, "no timestamps")
    return rows[:, 0]


def write_times(handle: TextIO, timestamps_s: np.ndarray) -> None:
    """One timestamp (s) per line, 7 significant digits (KITTI's own precision)."""
    for t in np.asarray(timestamps_s, dtype=np.float64).reshape(-1):
        handle.write(f"{t:e}\n")


@dataclass(frozen=True)
class KittiCalib:
    """A sequence's calib.txt: the projections P0, P1, ... (3, 4) of the rectified
    camera-0 frame into each camera's image, and the LiDAR's pose (4, 4)."""

    P_image_from_cam0: tuple[np.ndarray, ...] = field(repr=False)
    T_cam0_from_lidar: np.ndarray = field(repr=False)

    @classmethod
    def from_camera(
        cls,
        K: np.ndarray,
        T_cam0_from_lidar: np.ndarray,
        stereo_baseline_m: float = KITTI_STEREO_BASELINE_M,
    ) -> KittiCalib:
        """P0..P3 like KITTI's for camera matrix ``K`` (3, 3): cam 0 = K [I | 0]; cam 1 the
        right gray camera, ``stereo_baseline_m`` to the right (P1 = K [I | (-b, 0, 0)]);
        cams 2, 3 colour cameras (not recorded, listed as KITTI lists them)."""
        projections = []
        for baseline in (
            0.0,
            stereo_baseline_m,
            KITTI_COLOUR_OFFSET_M,
            KITTI_COLOUR_OFFSET_M + stereo_baseline_m,
        ):
            P = np.zeros((3, 4))
            P[:, :3] = K
            P[0, 3] = -K[0, 0] * baseline
            projections.append(P)
        return cls(tuple(projections), np.asarray(T_cam0_from_lidar, dtype=np.float64))

    @property
    def pinhole(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) of camera 0 (P0)."""
        P0 = self.P_image_from_cam0[0]
        return tuple(float(v) for v in (P0[0, 0], P0[1, 1], P0[0, 2], P0[1, 2]))

    def intrinsics(self, width_px: int, height_px: int) -> CameraIntrinsics:
        """Camera 0 with the images' size (calib.txt does not hold it)."""
        return CameraIntrinsics(*self.pinhole, width_px, height_px)

    def stereo_baseline_m(self) -> float:
        """The baseline (m) of the rectified pair P0 / P1: P1 = P0 but for its translation,
        camera 1 to the right of camera 0 (KITTI: 0.54 m); InvalidInputError otherwise."""
        if len(self.P_image_from_cam0) < 2:
            raise InvalidInputError("no P1 line: stereo depth needs the right camera's P1")
        P0, P1 = self.P_image_from_cam0[:2]
        tol = RECTIFIED_TOL * float(np.abs(P0[:, :3]).max())
        if not np.allclose(P1[:, :3], P0[:, :3], rtol=0.0, atol=tol) or not (
            np.isclose(P1[1, 3], P0[1, 3], atol=tol) and np.isclose(P1[2, 3], P0[2, 3], atol=tol)
        ):
            raise InvalidInputError(
                "P0 and P1 are not a rectified stereo pair (P1 must be P0 with only its "
                "x translation changed)"
            )
        baseline = float((P0[0, 3] - P1[0, 3]) / P0[0, 0])
        if not baseline > 0:
            raise InvalidInputError(
                f"P1 puts camera 1 {baseline:.4f} m along x: it must be to the right (> 0)"
            )
        return baseline


def _calib_fields(source: Source):
    path, lines = read_lines(source, "calibration")
    fields: dict[str, tuple[int, list[str]]] = {}
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        if not sep:
            raise InputFileError(path, "expected 'NAME: numbers'", number)
        fields[key.strip()] = (number, rest.split())
    return path, fields


def _matrix_3x4(path, fields: dict, key: str) -> np.ndarray:
    if key not in fields:
        raise InputFileError(path, f"no {key} line (KITTI calib.txt needs P0 and Tr)")
    number, values = fields[key]
    if len(values) != 12:
        raise InputFileError(path, f"{key} has {len(values)} numbers, expected 12 (3x4)", number)
    return np.array(finite_numbers(path, number, values, key)).reshape(3, 4)


def read_calib(source: Source) -> KittiCalib:
    """calib.txt -> KittiCalib. P0 must be a pinhole camera matrix (fx, fy > 0), every
    ``Pi`` and ``Tr`` 12 finite numbers, Tr rigid; P0 .. Pn must be consecutive."""
    path, fields = _calib_fields(source)
    P0 = _matrix_3x4(path, fields, "P0")
    fx, fy = P0[0, 0], P0[1, 1]
    pinhole = abs(P0[0, 1]) < 1e-9 and abs(P0[1, 0]) < 1e-9 and np.allclose(P0[2, :3], [0, 0, 1])
    if not pinhole or fx <= 0 or fy <= 0:
        raise InputFileError(
            path,
            "P0 is not a pinhole camera matrix [fx 0 cx tx; 0 fy cy ty; 0 0 1 tz]",
            fields["P0"][0],
        )
    indices = sorted(int(m.group(1)) for key in fields if (m := _PROJECTION_RE.match(key)))
    if indices != list(range(len(indices))):
        listed = ", ".join(f"P{i}" for i in indices)
        raise InputFileError(path, f"projections {listed} are not P0, P1, ... without a gap")
    projections = (P0, *(_matrix_3x4(path, fields, f"P{i}") for i in indices[1:]))
    T_cam0_from_lidar = _rigid_4x4(_matrix_3x4(path, fields, "Tr"))
    try:
        check_rigid(T_cam0_from_lidar, "Tr", tol=RIGID_TOL)
    except InvalidInputError as exc:
        raise InputFileError(path, str(exc), fields["Tr"][0]) from exc
    return KittiCalib(projections, T_cam0_from_lidar)


def _row(values: np.ndarray) -> str:
    # + 0.0 turns -0.0 into 0.0
    return " ".join(f"{v + 0.0:.12e}" for v in np.asarray(values, dtype=np.float64).ravel())


def write_calib(handle: TextIO, calib: KittiCalib) -> None:
    """``P0: 12 numbers`` ... then ``Tr: 12 numbers``, 13 significant digits."""
    for i, P in enumerate(calib.P_image_from_cam0):
        handle.write(f"P{i}: {_row(P)}\n")
    handle.write(f"Tr: {_row(np.asarray(calib.T_cam0_from_lidar)[:3, :4])}\n")


# ---- the layout: scans, sequences ------------------------------------------------------


def read_scan(path: str | os.PathLike) -> np.ndarray:
    """A velodyne .bin scan -> (N, 4) float32 (x, y, z, reflectance), LiDAR frame; points
    with a non-finite coordinate dropped. InputFileError naming the file if it cannot be
    read, is empty or is not a whole number of 16-byte points."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise InputFileError(path, f"cannot read LiDAR scan: {exc.strerror or exc}") from exc
    if not data:
        raise InputFileError(path, "LiDAR scan is empty")
    if len(data) % LIDAR_POINT_BYTES:
        raise InputFileError(
            path, f"LiDAR scan size {len(data)} bytes is not a multiple of {LIDAR_POINT_BYTES}"
        )
    points = np.frombuffer(data, dtype="<f4").reshape(-1, 4)
    finite = np.all(np.isfinite(points[:, :3]), axis=1)
    return points if finite.all() else points[finite]


def write_scan(path: str | os.PathLike, points: np.ndarray) -> None:
    """(N, 4) x, y, z, reflectance -> a velodyne .bin (little-endian float32)."""
    np.ascontiguousarray(points, dtype="<f4").tofile(path)


def image_name(index: int) -> str:
    """The file name (without suffix) of frame ``index``: ``%06d``."""
    return f"{index:06d}"


def sequence_dir(root: str | os.PathLike, sequence: str) -> Path:
    """``<root>/sequences/<sequence>``."""
    return Path(root) / "sequences" / sequence


def poses_path(root: str | os.PathLike, sequence: str) -> Path:
    """``<root>/poses/<sequence>.txt``."""
    return Path(root) / "poses" / f"{sequence}.txt"


@dataclass(frozen=True)
class KittiFrame:
    """One frame: index (the file number), timestamp, file paths and the z-up pose (4, 4)."""

    index: int
    timestamp_s: float
    image_path: Path
    scan_path: Path
    T_world_from_cam: np.ndarray = field(repr=False)
    right_image_path: Path | None = None


@dataclass(frozen=True)
class KittiSequence:
    """A validated KITTI sequence. ``frames`` holds the selected frames only;
    ``n_frames_total`` counts the whole sequence."""

    root: Path
    sequence: str
    calib_path: Path
    poses_path: Path
    intrinsics: CameraIntrinsics
    T_cam_from_lidar: np.ndarray = field(repr=False)
    frames: list[KittiFrame] = field(repr=False)
    n_frames_total: int = 0
    format: str = "kitti"
    read_skips: dict[str, int] = field(default_factory=dict)
    depth_from: str = "lidar"
    stereo_baseline_m: float | None = None

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    @property
    def name(self) -> str:
        """Where the run came from: ``<absolute sequence folder>`` (stored as the run's
        source name so a vocabulary change can find the images again)."""
        return str(self.root)


def resolve_sequence(root: str | os.PathLike, sequence: str | None) -> tuple[Path, str, Path]:
    """(sequence folder, sequence name, poses file) for a dataset root (``sequence``
    names NN; optional when there is only one) or a sequence folder."""
    root = Path(root).expanduser().resolve()
    if not root.is_dir():
        raise InputFileError(root, "KITTI path is not a directory")
    if (root / "calib.txt").exists() or (root / "image_0").is_dir():
        name = root.name
        if sequence is not None and sequence != name:
            raise InvalidInputError(f"{root} is sequence {name}, not {sequence}")
        local = root / "poses.txt"
        poses = local if local.exists() else poses_path(root.parent.parent, name)
        return root, name, poses
    sequences_dir = root / "sequences"
    if not sequences_dir.is_dir():
        raise InputFileError(
            root, "neither a KITTI dataset root (sequences/) nor a sequence folder"
        )
    available = sorted(p.name for p in sequences_dir.iterdir() if p.is_dir())
    if sequence is None:
        if len(available) != 1:
            raise InvalidInputError(
                f"{sequences_dir} holds sequences {available}: choose one with --sequence"
            )
        sequence = available[0]
    folder = sequence_dir(root, sequence)
    if not folder.is_dir():
        raise InputFileError(folder, f"no such sequence (available: {available})")
    return folder, sequence, poses_path(root, sequence)


def read_calib_file(path: str | os.PathLike) -> KittiCalib:
    """A sequence's calib.txt (``read_calib``), InputFileError when it is missing."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "calibration file is missing")
    return read_calib(path)


def read_stereo_baseline_m(path: str | os.PathLike) -> float:
    """``KittiCalib.stereo_baseline_m`` of a calib.txt, its errors naming the file."""
    try:
        return read_calib_file(path).stereo_baseline_m()
    except InputFileError:
        raise
    except InvalidInputError as exc:
        raise InputFileError(path, str(exc)) from exc


def read_poses_file(path: str | os.PathLike) -> np.ndarray:
    """poses/NN.txt (``read_poses``: T_kittiworld_from_cam, not yet z-up), InputFileError
    when it is missing."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "poses file is missing (KITTI poses/NN.txt)")
    return read_poses(path)


def _check_files(folder: Path, suffix: str, n: int, counted_by: Path) -> dict[str, int]:
    """Names %06d<suffix> for 0..n-1 must exist (and nothing beyond); returns name -> size."""
    if not folder.is_dir():
        raise InputFileError(folder, "folder is missing")
    sizes = {e.name: e.stat().st_size for e in os.scandir(folder) if e.name.endswith(suffix)}
    expected = [f"{image_name(i)}{suffix}" for i in range(n)]
    missing = [name for name in expected if name not in sizes]
    if missing:
        raise InputFileError(
            folder / missing[0],
            f"is missing ({len(missing)} of {n} files missing; {counted_by} has {n} frames)",
        )
    if len(sizes) != n:
        raise InputFileError(
            folder, f"holds {len(sizes)} {suffix} files but {counted_by} has {n} frames"
        )
    empty = [name for name in expected if sizes[name] == 0]
    if empty:
        raise InputFileError(folder / empty[0], "file is empty")
    return sizes


def _check_scans(folder: Path, n: int, counted_by: Path) -> None:
    for scan_name, size in _check_files(folder, ".bin", n, counted_by).items():
        if size % LIDAR_POINT_BYTES:
            raise InputFileError(
                folder / scan_name,
                f"size {size} bytes is not a multiple of {LIDAR_POINT_BYTES} (x, y, z, r float32)",
            )


def read_sequence(
    root: str | os.PathLike,
    sequence: str | None = None,
    frames: slice | None = None,
    depth_from: str = "lidar",
) -> KittiSequence:
    """Open and validate a KITTI odometry sequence as a mapping run.

    ``depth_from`` says where the keypoints' depth comes from: ``lidar`` (the velodyne
    scans, which must all be there) or ``stereo`` (the right camera: image_1 must hold one
    image per frame, of image_0's size, and calib.txt a P1 that forms a rectified pair
    with P0; velodyne/ is then not needed, so a fleet without LiDAR can map) or ``none``
    (the images only, for a vocabulary's training: neither velodyne/ nor image_1/ is read).

    Everything but the image and scan contents is validated: calib.txt (P0 a pinhole
    matrix, Tr rigid), one finite rigid pose per line, as many timestamps as poses, and
    every image and scan file of the whole sequence present (non-empty; scans a whole
    number of 16-byte points); frame counts agree across poses, times, image_0 and
    velodyne. Errors name the file and the line. The poses are converted to monoloc's
    z-up world (``kitti_to_zup``). ``frames`` selects frame indices with Python slice
    semantics (``slice(0, 3860)``: frames 0..3859), applied after the whole sequence was
    validated.
    """
    if depth_from not in DEPTH_SOURCES:
        raise InvalidInputError(f"unknown depth source {depth_from!r}: use lidar or stereo")
    folder, name, poses_path = resolve_sequence(root, sequence)
    calib_path = folder / "calib.txt"
    calib = read_calib_file(calib_path)
    stereo = depth_from == "stereo"
    baseline_m = read_stereo_baseline_m(calib_path) if stereo else None
    poses = read_poses_file(poses_path)
    n = len(poses)
    times_path = folder / "times.txt"
    if not times_path.is_file():
        raise InputFileError(times_path, "times file is missing")
    times = read_times(times_path)
    if len(times) != n:
        raise InputFileError(
            times_path, f"has {len(times)} timestamps but {poses_path} has {n} poses"
        )
    _check_files(folder / "image_0", ".png", n, poses_path)
    width, height = png_size(folder / "image_0" / f"{image_name(0)}.png")
    if stereo:
        _check_files(folder / "image_1", ".png", n, poses_path)
        right_size = png_size(folder / "image_1" / f"{image_name(0)}.png")
        if right_size != (width, height):
            raise InputFileError(
                folder / "image_1" / f"{image_name(0)}.png",
                f"is {right_size[0]}x{right_size[1]}, image_0 is {width}x{height}: a "
                "rectified pair has one size",
            )
    elif depth_from == "lidar":
        _check_scans(folder / "velodyne", n, poses_path)
    T_world_from_cam = kitti_to_zup(poses)
    indices = range(n)[frames] if frames is not None else range(n)
    selected = [
        KittiFrame(
            index=i,
            timestamp_s=float(times[i]),
            image_path=folder / "image_0" / f"{image_name(i)}.png",
            scan_path=folder / "velodyne" / f"{image_name(i)}.bin",
            T_world_from_cam=T_world_from_cam[i],
            right_image_path=folder / "image_1" / f"{image_name(i)}.png" if stereo else None,
        )
        for i in indices
    ]
    return KittiSequence(
        root=folder,
        sequence=name,
        calib_path=calib_path,
        poses_path=poses_path,
        intrinsics=calib.intrinsics(width, height),
        T_cam_from_lidar=calib.T_cam0_from_lidar,
        frames=selected,
        n_frames_total=n,
        depth_from=depth_from,
        stereo_baseline_m=baseline_m,
    )

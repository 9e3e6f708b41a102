"""Reader of KITTI odometry sequences (and of the sim's output, which has the same layout).

Layout (the real dataset's)::

    <root>/sequences/NN/calib.txt        "P0: 12 numbers" ... "Tr: 12 numbers"
    <root>/sequences/NN/times.txt        one timestamp (s) per frame
    <root>/sequences/NN/image_0/%06d.png grayscale left camera
    <root>/sequences/NN/image_1/%06d.png grayscale right camera (read with depth_from="stereo")
    <root>/sequences/NN/velodyne/%06d.bin float32 (x, y, z, reflectance) in the LiDAR frame
    <root>/poses/NN.txt                  3x4 T_kittiworld_from_cam0 per line, row-major

``depth_from`` says where the keypoints' depth comes from: ``lidar`` (the default: the
velodyne scans, which must all be there) or ``stereo`` (the right camera: image_1 must
hold one image per frame, of image_0's size, and calib.txt a P1 that forms a rectified
pair with P0: the same camera matrix, the right camera along +x; velodyne/ is then not
needed, so a fleet without LiDAR can map).

``root`` may be the dataset root (``sequence`` names NN; optional when there is only
one sequence) or a sequence folder itself; then the poses are ``<seq>/poses.txt`` if
present, else ``<seq>/../../poses/NN.txt``.

Everything but the image and scan contents is validated when the sequence is opened,
before anything is written: calib.txt (P0 a 3x4 pinhole matrix, Tr a 3x4 rigid
transform), one finite rigid pose per line (the text formats are
``monoloc.core.formats.kitti``), as many timestamps as poses, and every
image and scan file of the whole sequence present (non-empty; scans a whole number of
16-byte points). Frame counts must agree across poses, times, image_0 and velodyne.
Errors name the file and the line.

KITTI's world is its first camera frame (x right, y down, z forward); the poses are
converted to monoloc's z-up world by ``monoloc.core.geometry.kitti_to_zup`` (the one place
that conversion lives). ``frames`` selects a range of frame indices with Python slice
semantics (``slice(0, 3860)``: frames 0..3859), applied after the whole sequence was
validated.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.formats import kitti as kitti_format
from monoloc.core.geometry import kitti_to_zup
from monoloc.server.ingest.common import LoadedFrame, decode_gray, png_size, read_bytes

LIDAR_POINT_BYTES = 16  # float32 x, y, z, reflectance
DEPTH_SOURCES = ("lidar", "stereo")
RECTIFIED_TOL = 1e-6  # relative: P1's camera matrix must equal P0's


@dataclass(frozen=True)
class KittiCalibration:
    """Camera 0 intrinsics (without image size) and the LiDAR-to-camera-0 transform."""

    fx: float
    fy: float
    cx: float
    cy: float
    T_cam_from_lidar: np.ndarray

    def intrinsics(self, width_px: int, height_px: int) -> CameraIntrinsics:
        return CameraIntrinsics(self.fx, self.fy, self.cx, self.cy, width_px, height_px)


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

    def load(self, frame: KittiFrame) -> LoadedFrame:
        """Read the frame's image and scan, or its right image when the depth comes from
        stereo (thread-safe; no database access)."""
        from monoloc.server.entry_builder import LidarSource, StereoSource

        data = read_bytes(frame.image_path, "image")
        image = decode_gray(data, frame.image_path)
        if self.depth_from == "stereo":
            right_path = frame.right_image_path
            assert right_path is not None and self.stereo_baseline_m is not None
            right = decode_gray(read_bytes(right_path, "image"), right_path)
            if right.shape != image.shape:
                raise InputFileError(
                    right_path,
                    f"right image is {right.shape[1]}x{right.shape[0]}, the left "
                    f"{image.shape[1]}x{image.shape[0]}: a rectified pair has one size",
                )
            return LoadedFrame(data, image, StereoSource(right, self.stereo_baseline_m))
        return LoadedFrame(
            data, image, LidarSource(read_scan(frame.scan_path), self.T_cam_from_lidar)
        )


def read_scan(path: Path) -> np.ndarray:
    """A KITTI .bin scan -> (N, 4) float32 (x, y, z, reflectance), LiDAR frame."""
    data = read_bytes(path, "LiDAR scan")
    if len(data) % LIDAR_POINT_BYTES:
        raise InputFileError(
            path, f"LiDAR scan size {len(data)} bytes is not a multiple of {LIDAR_POINT_BYTES}"
        )
    points = np.frombuffer(data, dtype="<f4").reshape(-1, 4)
    finite = np.all(np.isfinite(points[:, :3]), axis=1)
    return points if finite.all() else points[finite]


def read_kitti_calibration(path: Path) -> KittiCalibration:
    """A KITTI odometry calib.txt: P0 -> intrinsics; Tr -> T_cam_from_lidar."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "calibration file is missing")
    calib = kitti_format.read_calib(path)
    P0 = calib.P_image_from_cam0[0]
    fx, fy, cx, cy = (float(v) for v in (P0[0, 0], P0[1, 1], P0[0, 2], P0[1, 2]))
    return KittiCalibration(fx, fy, cx, cy, calib.T_cam0_from_lidar)


def stereo_baseline_m(path: Path) -> float:
    """The baseline (m) of the rectified pair P0 / P1 of a calib.txt: P1 = P0 but for
    its translation, camera 1 to the right of camera 0 (KITTI: 0.54 m); InputFileError
    naming the file otherwise."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "calibration file is missing")
    projections = kitti_format.read_calib(path).P_image_from_cam0
    if len(projections) < 2:
        raise InputFileError(path, "no P1 line: stereo depth needs the right camera's P1")
    P0, P1 = projections[0], projections[1]
    scale = float(np.abs(P0[:, :3]).max())
    if not np.allclose(P1[:, :3], P0[:, :3], rtol=0.0, atol=RECTIFIED_TOL * scale) or not (
        np.isclose(P1[1, 3], P0[1, 3], atol=RECTIFIED_TOL * scale)
        and np.isclose(P1[2, 3], P0[2, 3], atol=RECTIFIED_TOL * scale)
    ):
        raise InputFileError(
            path,
            "P0 and P1 are not a rectified stereo pair (P1 must be P0 with only its "
            "x translation changed)",
        )
    baseline = float((P0[0, 3] - P1[0, 3]) / P0[0, 0])
    if not baseline > 0:
        raise InputFileError(
            path, f"P1 puts camera 1 {baseline:.4f} m along x: it must be to the right (> 0)"
        )
    return baseline


def read_kitti_poses(path: Path) -> np.ndarray:
    """poses/NN.txt -> (N, 4, 4) T_kittiworld_from_cam (KITTI's world, not yet z-up)."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "poses file is missing (KITTI poses/NN.txt)")
    return kitti_format.read_poses(path)


def _resolve(root: Path, sequence: str | None) -> tuple[Path, str, Path]:
    """(sequence folder, sequence name, poses file) for a dataset root or sequence folder."""
    root = Path(root).expanduser().resolve()
    if not root.is_dir():
        raise InputFileError(root, "KITTI path is not a directory")
    if (root / "calib.txt").exists() or (root / "image_0").is_dir():
        name = root.name
        if sequence is not None and sequence != name:
            raise InvalidInputError(f"{root} is sequence {name}, not {sequence}")
        local = root / "poses.txt"
        poses = local if local.exists() else root.parent.parent / "poses" / f"{name}.txt"
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
    folder = sequences_dir / sequence
    if not folder.is_dir():
        raise InputFileError(folder, f"no such sequence (available: {available})")
    return folder, sequence, root / "poses" / f"{sequence}.txt"


def _check_files(folder: Path, suffix: str, n: int, counted_by: Path) -> dict[str, int]:
    """Names %06d<suffix> for 0..n-1 must exist (and nothing beyond); returns name -> size."""
    if not folder.is_dir():
        raise InputFileError(folder, "folder is missing")
    sizes = {e.name: e.stat().st_size for e in os.scandir(folder) if e.name.endswith(suffix)}
    expected = [f"{i:06d}{suffix}" for i in range(n)]
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


def read_kitti_sequence(
    root: Path,
    sequence: str | None = None,
    frames: slice | None = None,
    depth_from: str = "lidar",
) -> KittiSequence:
    """Open and validate a KITTI odometry sequence (see the module docstring)."""
    if depth_from not in DEPTH_SOURCES:
        raise InvalidInputError(f"unknown depth source {depth_from!r}: use lidar or stereo")
    folder, name, poses_path = _resolve(Path(root), sequence)
    calib_path = folder / "calib.txt"
    calibration = read_kitti_calibration(calib_path)
    stereo = depth_from == "stereo"
    baseline_m = stereo_baseline_m(calib_path) if stereo else None
    poses = read_kitti_poses(poses_path)
    n = len(poses)
    times_path = folder / "times.txt"
    if not times_path.is_file():
        raise InputFileError(times_path, "times file is missing")
    times = kitti_format.read_times(times_path)
    if len(times) != n:
        raise InputFileError(
            times_path, f"has {len(times)} timestamps but {poses_path} has {n} poses"
        )
    _check_files(folder / "image_0", ".png", n, poses_path)
    width, height = png_size(folder / "image_0" / "000000.png")
    if stereo:
        _check_files(folder / "image_1", ".png", n, poses_path)
        right_size = png_size(folder / "image_1" / "000000.png")
        if right_size != (width, height):
            raise InputFileError(
                folder / "image_1" / "000000.png",
                f"is {right_size[0]}x{right_size[1]}, image_0 is {width}x{height}: a "
                "rectified pair has one size",
            )
    else:
        _check_scans(folder / "velodyne", n, poses_path)
    T_world_from_cam = kitti_to_zup(poses)
    indices = range(n)[frames] if frames is not None else range(n)
    selected = [
        KittiFrame(
            index=i,
            timestamp_s=float(times[i]),
            image_path=folder / "image_0" / f"{i:06d}.png",
            scan_path=folder / "velodyne" / f"{i:06d}.bin",
            T_world_from_cam=T_world_from_cam[i],
            right_image_path=folder / "image_1" / f"{i:06d}.png" if stereo else None,
        )
        for i in indices
    ]
    return KittiSequence(
        root=folder,
        sequence=name,
        calib_path=calib_path,
        poses_path=poses_path,
        intrinsics=calibration.intrinsics(width, height),
        T_cam_from_lidar=calibration.T_cam_from_lidar,
        frames=selected,
        n_frames_total=n,
        depth_from=depth_from,
        stereo_baseline_m=baseline_m,
    )

"""Reading a recorded run the way a vehicle would replay it: frames, signals, truth.

KITTI odometry (``image_0/``, ``times.txt``, ``vehicle.txt``, the poses) and TUM RGB-D
(``rgb.txt``, ``groundtruth.txt``, ``vehicle.txt``). ``vehicle.txt`` holds one line per
frame: ``t speed_mps yaw_rate_radps``. A KITTI sequence without it gets speed and yaw rate
derived from its poses plus configurable noise, and says so. The layouts and the files'
formats are ``monoloc.core.formats`` (where a sequence's poses are, what a file list
holds); this module aligns them into a run.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError, NotFoundError
from monoloc.core.formats import kitti, tum, vehicle
from monoloc.core.formats.png import png_size
from monoloc.core.geometry import (
    kitti_to_zup,
    planar_from_T_world_from_cam,
    wrap_angle,
)


@dataclass(frozen=True)
class SignalNoise:
    """Noise added to speed and yaw rate derived from ground-truth poses."""

    speed_std_mps: float = 0.05
    yaw_rate_std_radps: float = 0.005
    seed: int = 0


@dataclass(frozen=True)
class ReplayRun:
    """Frames of one run, aligned: image paths (N,), timestamps (N,), signals (N, 2) of
    (speed_mps, yaw_rate_radps), and planar ground truth (N, 3) or None."""

    name: str
    image_paths: list[Path]
    timestamps_s: np.ndarray
    signals: np.ndarray
    truth_world: np.ndarray | None
    notes: list[str] = field(default_factory=list)
    # Camera ahead of the speed reference point (m), when the recording says so.
    lever_arm_m: float | None = None
    # How to read an image's encoded bytes from its entry of ``image_paths``: the file's
    # bytes by default; a ROS bag's images are messages (monoloc.client.bag_replay).
    read_image: Callable[[Path], bytes] | None = field(default=None, repr=False)
    # The camera's frame id when the recording names it (a ROS bag's image frame_id).
    camera_frame: str | None = None
    # The camera that took the frames, when the recording says (KITTI calib.txt's P0 with
    # the images' size, a TUM run's camera.json, a bag's CameraInfo): the vehicle sends it
    # with every frame, never assuming the map's.
    intrinsics: CameraIntrinsics | None = None

    def __len__(self) -> int:
        return len(self.image_paths)

    def image_bytes(self, i: int) -> bytes:
        """The encoded (PNG/JPEG) image of frame ``i``."""
        path = self.image_paths[i]
        return path.read_bytes() if self.read_image is None else self.read_image(path)

    def select(self, frames: slice) -> ReplayRun:
        """The frames ``frames`` selects (python slice semantics), e.g. the test part."""
        idx = range(len(self))[frames]
        truth = None if self.truth_world is None else self.truth_world[frames]
        notes = list(self.notes)
        if len(idx) != len(self):
            first = f"{idx[0]}..{idx[-1]}" if len(idx) else "none"
            notes.append(f"frames {first} of {len(self)} selected ({len(idx)} frames)")
        return ReplayRun(
            self.name,
            [self.image_paths[i] for i in idx],
            self.timestamps_s[frames],
            self.signals[frames],
            truth,
            notes,
            self.lever_arm_m,
            self.read_image,
            self.camera_frame,
            self.intrinsics,
        )

    def with_intrinsics(self, intrinsics: CameraIntrinsics) -> ReplayRun:
        """The same run taken with ``intrinsics`` (a camera given on the command line)."""
        return dataclasses.replace(self, intrinsics=intrinsics)


def parse_frames(text: str | None) -> slice:
    """'A:B' (python slice semantics, either side optional) -> slice."""
    if not text:
        return slice(None)
    try:
        parts = [int(p) if p.strip() else None for p in text.split(":")]
    except ValueError as exc:
        raise InvalidInputError(f"--frames must look like A:B, got {text!r}") from exc
    if len(parts) != 2:
        raise InvalidInputError(f"--frames must look like A:B, got {text!r}")
    return slice(parts[0], parts[1])


def signals_from_truth(
    timestamps_s: np.ndarray, truth_world: np.ndarray, noise: SignalNoise
) -> np.ndarray:
    """Speed and yaw rate (N, 2) by finite differences of planar poses, plus noise."""
    rng = np.random.default_rng(noise.seed)
    dt = np.diff(timestamps_s)
    dt = np.where(dt > 0, dt, np.nan)
    speed = np.linalg.norm(np.diff(truth_world[:, :2], axis=0), axis=1) / dt
    yaw_rate = wrap_angle(np.diff(truth_world[:, 2])) / dt
    signals = np.zeros((len(timestamps_s), 2))
    signals[:-1, 0], signals[:-1, 1] = speed, yaw_rate
    signals[-1] = signals[-2] if len(signals) > 1 else 0.0
    signals = np.nan_to_num(signals)
    signals[:, 0] += rng.normal(scale=noise.speed_std_mps, size=len(signals))
    signals[:, 1] += rng.normal(scale=noise.yaw_rate_std_radps, size=len(signals))
    return signals


def _vehicle_signals(path: Path, timestamps_s: np.ndarray) -> np.ndarray:
    """(speed_mps, yaw_rate_radps) (N, 2) from vehicle.txt, one line per frame, whose times
    match the frames' (within a quarter of the frame period)."""
    signals = vehicle.read_vehicle(path)
    n = len(timestamps_s)
    if len(signals) != n:
        raise InvalidInputError(f"{path}: {len(signals)} lines for {n} frames")
    period = float(np.median(np.diff(timestamps_s))) if n > 1 else 0.0
    tolerance = max(0.25 * period, 1e-3)
    off = np.abs(signals.timestamps_s - timestamps_s)
    if n and off.max() > tolerance:
        row = int(np.flatnonzero(off > tolerance)[0])
        raise InvalidInputError(
            f"{path}: data row {row + 1} has time {signals.timestamps_s[row]:.6f} s but frame "
            f"{row} is at {timestamps_s[row]:.6f} s"
        )
    return np.column_stack([signals.speed_mps, signals.yaw_rate_radps])


def read_kitti_run(
    root: Path, sequence: str | None = None, noise: SignalNoise = SignalNoise()
) -> ReplayRun:
    """A KITTI sequence: ``root`` is the dataset root (with ``sequence``, optional when it
    holds one) or the sequence folder (``kitti.resolve_sequence``)."""
    seq_dir, seq_name, poses_path = kitti.resolve_sequence(root, sequence)
    if not (seq_dir / "image_0").is_dir():
        raise NotFoundError(f"{seq_dir / 'image_0'} does not exist")
    images = sorted((seq_dir / "image_0").glob("*.png"))
    if not images:
        raise InvalidInputError(f"{seq_dir / 'image_0'} holds no PNG images")
    times_path = seq_dir / "times.txt"
    if not times_path.exists():
        raise NotFoundError(f"{times_path} does not exist")
    times = kitti.read_times(times_path)
    if len(times) != len(images):
        raise InvalidInputError(f"{times_path}: {len(times)} lines for {len(images)} images")
    truth = None
    if poses_path.exists():
        T_kittiworld_from_cam = kitti.read_poses(poses_path)
        if len(T_kittiworld_from_cam) != len(images):
            raise InvalidInputError(
                f"{poses_path}: {len(T_kittiworld_from_cam)} poses for {len(images)} images"
            )
        truth = planar_from_T_world_from_cam(kitti_to_zup(T_kittiworld_from_cam))
    notes = []
    vehicle_path = seq_dir / "vehicle.txt"
    if vehicle_path.exists():
        signals = _vehicle_signals(vehicle_path, times)
    elif truth is not None:
        signals = signals_from_truth(times, truth, noise)
        notes.append(
            f"no vehicle.txt: speed and yaw rate derived from {poses_path.name} with noise "
            f"{noise.speed_std_mps} m/s, {noise.yaw_rate_std_radps} rad/s"
        )
    else:
        raise InvalidInputError(f"{seq_dir}: neither vehicle.txt nor ground-truth poses")
    intrinsics = None
    if (seq_dir / "calib.txt").is_file():
        intrinsics = kitti.read_calib_file(seq_dir / "calib.txt").intrinsics(*png_size(images[0]))
    return ReplayRun(
        f"kitti:{seq_name}", images, times, signals, truth, notes, intrinsics=intrinsics
    )


def read_tum_run(root: Path, max_dt_s: float = 0.02) -> ReplayRun:
    """A TUM RGB-D run: rgb.txt frames, groundtruth.txt truth (nearest within max_dt_s)."""
    root = Path(root)
    rgb_path = root / "rgb.txt"
    if not rgb_path.exists():
        raise NotFoundError(f"{rgb_path} does not exist")
    times_arr, names = tum.read_file_list(rgb_path, root=root)  # every image must exist
    images = [root / name for name in names]
    truth = None
    gt_path = root / "groundtruth.txt"
    if gt_path.exists():
        gt = tum.read_trajectory(gt_path)
        gt_t = gt.timestamps_s
        idx = np.clip(np.searchsorted(gt_t, times_arr), 1, len(gt_t) - 1)
        nearest = np.where(
            np.abs(gt_t[idx - 1] - times_arr) <= np.abs(gt_t[idx] - times_arr), idx - 1, idx
        )
        if np.any(np.abs(gt_t[nearest] - times_arr) > max_dt_s):
            raise InvalidInputError(f"{gt_path}: no ground truth within {max_dt_s} s of a frame")
        T = gt.T_world_from_cam[nearest]
        truth = planar_from_T_world_from_cam(T)
    vehicle_path = root / "vehicle.txt"
    if not vehicle_path.exists():
        raise NotFoundError(f"{vehicle_path} does not exist")
    signals = _vehicle_signals(vehicle_path, times_arr)
    intrinsics = tum.read_run_camera(root, images[0]) if images else None
    return ReplayRun(
        f"tum:{root.name}", images, times_arr, signals, truth, [], intrinsics=intrinsics
    )


def rig_lever_arm_m(path: Path) -> float | None:
    """The camera's distance ahead of the speed reference point, from a ``dataset.json``
    (monoloc's sim writes ``rig.T_vehicle_from_cam0``, indoors ``T_vehicle_from_cam``) at or
    above ``path``; None if absent."""
    import json

    for folder in [path, *path.parents][:4]:
        meta = folder / "dataset.json"
        if meta.exists():
            try:
                rig = json.loads(meta.read_text()).get("rig") or {}
                key = next(k for k in ("T_vehicle_from_cam0", "T_vehicle_from_cam") if k in rig)
                return float(np.asarray(rig[key], dtype=float)[0, 3])
            except (ValueError, KeyError, TypeError, IndexError, StopIteration):
                return None
    return None


def read_run(path: Path, sequence: str | None = None) -> ReplayRun:
    """KITTI or TUM, recognised by its files; picks up the rig's lever arm if recorded."""
    path = Path(path)
    run = read_tum_run(path) if (path / "rgb.txt").exists() else read_kitti_run(path, sequence)
    lever = rig_lever_arm_m(path)
    if lever is not None:
        note = f"camera {lever:.2f} m ahead of the speed reference (dataset.json rig)"
        run = dataclasses.replace(run, notes=[*run.notes, note], lever_arm_m=lever)
    return run

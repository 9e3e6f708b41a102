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
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InputFileError, InvalidInputError, NotFoundError
from monoloc.core.formats import kitti, tum, vehicle
from monoloc.core.formats.camera_yaml import CAMERA_YAML, CameraFile, read_camera_yaml
from monoloc.core.formats.png import png_size
from monoloc.core.geometry import (
    kitti_to_zup,
    planar_from_T_world_from_cam,
    wrap_angle,
)
from monoloc.core.mounting import CameraMounting


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
    # Where the camera sits on the vehicle (T_vehicle_from_cam), when the rig says: a
    # camera.yaml / camera.json beside the frames, dataset.json, a bag's /tf_static.
    # ``lever_arm_m`` is then its lever arm.
    mounting: CameraMounting | None = None

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
        return dataclasses.replace(
            self,
            image_paths=[self.image_paths[i] for i in idx],
            timestamps_s=self.timestamps_s[frames],
            signals=self.signals[frames],
            truth_world=truth,
            notes=notes,
        )

    def with_intrinsics(self, intrinsics: CameraIntrinsics) -> ReplayRun:
        """The same run taken with ``intrinsics`` (a camera given on the command line)."""
        return dataclasses.replace(self, intrinsics=intrinsics)

    def with_mounting(self, mounting: CameraMounting | None, note: str | None = None) -> ReplayRun:
        """The same run with the camera at ``mounting`` on the vehicle (its lever arm too)."""
        notes = self.notes if note is None else [*self.notes, note]
        lever = None if mounting is None else mounting.lever_arm_m
        return dataclasses.replace(self, mounting=mounting, lever_arm_m=lever, notes=notes)


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
    camera = read_run_camera_file(seq_dir, images[0])
    mounting = None
    if camera is not None:  # its lens and mounting; its K must be calib.txt's P0
        if intrinsics is not None and not _same_pinhole(intrinsics, camera.intrinsics):
            raise InputFileError(
                camera.path,
                f"its camera matrix {_focal_text(camera.intrinsics)} is not calib.txt's P0 "
                f"{_focal_text(intrinsics)}",
            )
        intrinsics, mounting = camera.intrinsics, camera.mounting
    return ReplayRun(
        f"kitti:{seq_name}",
        images,
        times,
        signals,
        truth,
        notes,
        intrinsics=intrinsics,
        mounting=mounting,
    )


def _same_pinhole(a: CameraIntrinsics, b: CameraIntrinsics, tol_px: float = 0.01) -> bool:
    return (a.width_px, a.height_px) == (b.width_px, b.height_px) and all(
        abs(x - y) <= tol_px for x, y in zip(a.K.ravel(), b.K.ravel(), strict=True)
    )


def _focal_text(k: CameraIntrinsics) -> str:
    return f"(fx {k.fx:g}, fy {k.fy:g}, cx {k.cx:g}, cy {k.cy:g}, {k.width_px}x{k.height_px})"


def read_run_camera_file(folder: Path, first_image: Path | None) -> CameraFile | None:
    """The camera a run's folder describes: ``camera.yaml`` (ROS's calibration layout,
    monoloc.core.formats.camera_yaml), else a camera JSON (``camera.json``,
    ``intrinsics.json``: fx, fy, cx, cy, width, height, distortion_model, D), with its
    mounting (``T_vehicle_from_cam`` or ``mounting``) when given; None without one."""
    folder = Path(folder)
    if (folder / CAMERA_YAML).is_file():
        return read_camera_yaml(folder / CAMERA_YAML)
    json_path, data = tum.read_camera_json(folder)
    if json_path is None or first_image is None:
        return None
    intrinsics = tum.read_run_camera(folder, first_image)
    mounting = None
    try:
        if data.get("T_vehicle_from_cam") is not None:
            mounting = CameraMounting.from_dict({"T_vehicle_from_cam": data["T_vehicle_from_cam"]})
        elif data.get("mounting") is not None:
            mounting = CameraMounting.from_dict(data["mounting"])
    except InvalidInputError as exc:
        raise InputFileError(json_path, str(exc)) from exc
    return CameraFile(json_path, intrinsics, mounting)


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
    camera = read_run_camera_file(root, images[0] if images else None)
    return ReplayRun(
        f"tum:{root.name}",
        images,
        times_arr,
        signals,
        truth,
        [],
        intrinsics=None if camera is None else camera.intrinsics,
        mounting=None if camera is None else camera.mounting,
    )


def rig_mounting(path: Path, sequence: str | None = None) -> CameraMounting | None:
    """Where the camera sits on the vehicle, from a ``dataset.json`` at or above ``path``:
    the sequence's own ``T_vehicle_from_cam`` (a run recorded by another camera), else
    the rig's (monoloc's sim writes ``rig.T_vehicle_from_cam0``, indoors
    ``T_vehicle_from_cam``), or a ``mounting`` mapping (CameraMounting's fields); None if
    absent. A malformed one raises InputFileError."""
    import json

    for folder in [path, *path.parents][:4]:
        meta = folder / "dataset.json"
        if not meta.exists():
            continue
        try:
            info = json.loads(meta.read_text())
        except (OSError, ValueError) as exc:
            raise InputFileError(meta, f"cannot read: {exc}") from exc
        if not isinstance(info, dict):
            return None
        for entry in info.get("sequences") or []:
            if isinstance(entry, dict) and sequence is not None and entry.get("id") == sequence:
                if entry.get("T_vehicle_from_cam") is not None:
                    return _mounting(meta, {"T_vehicle_from_cam": entry["T_vehicle_from_cam"]})
        rig = info.get("rig") or {}
        for key in ("T_vehicle_from_cam0", "T_vehicle_from_cam"):
            if isinstance(rig, dict) and rig.get(key) is not None:
                return _mounting(meta, {"T_vehicle_from_cam": rig[key]})
        if isinstance(rig, dict) and rig.get("mounting") is not None:
            return _mounting(meta, rig["mounting"])
        return None
    return None


def _mounting(path: Path, data: dict) -> CameraMounting:
    try:
        return CameraMounting.from_dict(data)
    except InvalidInputError as exc:
        raise InputFileError(path, str(exc)) from exc


def rig_lever_arm_m(path: Path) -> float | None:
    """The camera's distance ahead of the speed reference point (``rig_mounting``)."""
    mounting = rig_mounting(path)
    return None if mounting is None else mounting.lever_arm_m


def mounting_note(mounting: CameraMounting, source: str) -> str:
    """One line saying where the camera sits, for a drive's notes."""
    return (
        f"camera {mounting.lever_arm_m:.2f} m ahead, {mounting.lateral_m:.2f} m left, "
        f"{mounting.height_m:.2f} m above the speed reference; yaw "
        f"{math.degrees(mounting.yaw_rad):.2f} deg, pitch {math.degrees(mounting.pitch_rad):.2f} "
        f"deg, roll {math.degrees(mounting.roll_rad):.2f} deg ({source})"
    )


def read_run(path: Path, sequence: str | None = None) -> ReplayRun:
    """KITTI or TUM, recognised by its files; picks up where the camera sits when the
    recording says: its camera file (camera.yaml, camera.json) first, else dataset.json."""
    path = Path(path)
    run = read_tum_run(path) if (path / "rgb.txt").exists() else read_kitti_run(path, sequence)
    if run.mounting is not None:
        return run.with_mounting(run.mounting, mounting_note(run.mounting, "the camera file"))
    seq = sequence if sequence is not None else run.name.removeprefix("kitti:")
    mounting = rig_mounting(path, seq)
    if mounting is not None:
        run = run.with_mounting(mounting, mounting_note(mounting, "dataset.json rig"))
    return run

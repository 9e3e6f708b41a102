"""kapture datasets, read and written through the ``kapture`` package.

Reading (a mapping run): ``sensors.txt`` cameras (kapture's camera types, read as
COLMAP's models with their lens distortion, which the import takes off; ``FOV``,
``THIN_PRISM_FISHEYE`` and ``UNKNOWN_CAMERA`` refused by name), ``rigs.txt`` (rig poses are
resolved into sensor poses with kapture's own ``rigs_remove``), ``trajectories.txt``
(kapture stores ``device_from_world``), ``records_camera.txt``, and per image one 3D
source, first found of:

1. a depth map (``records_depth.txt``, kapture's float32 metres) at the same timestamp
   from a depth sensor of the same size and intrinsics whose pose, when it has one, is
   the camera's (a registered depth map);
2. a LiDAR scan (``records_lidar.txt``) at the same timestamp, a ``.bin`` file of float32
   x, y, z, reflectance (KITTI's layout) in the LiDAR's frame, whose pose at that
   timestamp gives ``T_cam_from_lidar``;
3. the reconstruction: ORB/any 2D keypoints of the image with ``observations.txt`` of
   ``points3d.txt`` (as COLMAP's observations; see ``formats.model`` for the two ways).

An image without a pose or a 3D source is skipped (``no_pose`` / ``no_3d_source``).
kapture fixes no world axes: monoloc takes it as z-up (GNSS/LiDAR-mapped datasets; a
monoloc export says so in ``monoloc.json``); give ``--up -y`` for one converted from an
SfM model. Pixels: kapture's converters copy COLMAP's camera numbers as they are, so its
convention is taken as COLMAP's (centre of pixel (0, 0) at (0.5, 0.5)).

Writing (a map): a camera sensor per distinct intrinsics (``cam0``, ...; its kapture
type from its distortion, ``PINHOLE`` for a map's camera), one record and one pose per
entry (the entry id as timestamp; image ``entry_<id>.jpg`` under
``sensors/records_data``, the entry's stored preview), the entries' ORB keypoints and
descriptors (types ``orb``, Hamming), their 3D points (shared by several entries where
the export merged them into one track) and observations. A driven
trajectory (TUM or KITTI file of ``monoloc drive``) is written as ``trajectories.txt`` of
device ``cam0`` with timestamps in microseconds.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.geometry import (
    R_from_quaternion_xyzw,
    invert_rigid,
    quaternion_xyzw_from_R,
)
from monoloc.server.formats.model import (
    MARKER_FILE,
    PIXEL_SHIFT,
    ModelView,
    PosedImage,
    PosedImages,
    camera_intrinsics,
    camera_model_of,
    read_marker_up,
    tracks_of,
)

CAMERA_ID = "cam0"
FEATURE_TYPE = "orb"


def _import_kapture():
    try:
        import kapture
        import kapture.io.csv  # noqa: F401  (kapture_from_dir / kapture_to_dir)
    except ImportError as exc:  # the `formats` extra
        raise InvalidInputError(
            "kapture support needs kapture: pip install 'monoloc[formats]'"
        ) from exc
    return kapture


@dataclass(frozen=True)
class DepthMapFile:
    """A kapture depth map (float32 metres, 0 = none), read when the frame is built."""

    path: Path
    size: tuple[int, int]  # (width, height)

    def load(self):
        from kapture.io.records import depth_map_from_file

        from monoloc.server.entry_builder import DepthSource

        expected = self.size[0] * self.size[1] * 4
        if not self.path.is_file() or self.path.stat().st_size != expected:
            raise InputFileError(
                self.path, f"depth map missing or not {self.size[0]}x{self.size[1]} float32"
            )
        depth_m = depth_map_from_file(str(self.path), self.size)
        return DepthSource(np.where(np.isfinite(depth_m) & (depth_m > 0), depth_m, 0.0), 1.0)


@dataclass(frozen=True)
class LidarFile:
    """A LiDAR scan (.bin float32 x, y, z, r) and T_cam_from_lidar (4, 4)."""

    path: Path
    T_cam_from_lidar: np.ndarray

    def load(self):
        from monoloc.core.formats.kitti import read_scan
        from monoloc.server.entry_builder import LidarSource

        return LidarSource(read_scan(self.path), self.T_cam_from_lidar)


def _intrinsics(sensor, where: str) -> CameraIntrinsics:
    params = [float(v) for v in sensor.camera_params]  # width, height, then the model's
    return camera_intrinsics(
        sensor.camera_type.name,
        params[2:],
        int(params[0]),
        int(params[1]),
        f"{where}: camera {sensor.name or ''}",
    )


def _matrix(pose) -> np.ndarray | None:
    """A kapture PoseTransform as a (4, 4) matrix of what it maps (a_from_b); None for a
    partial pose (rotation or translation unknown)."""
    if pose.r is None or pose.t is None:
        return None
    w, x, y, z = (float(v) for v in pose.r_raw)
    T = np.eye(4)
    T[:3, :3] = R_from_quaternion_xyzw(np.array([x, y, z, w]))
    T[:3, 3] = np.asarray(pose.t_raw, dtype=np.float64).ravel()
    return T


def _pose(T_a_from_b: np.ndarray):
    import kapture

    q = quaternion_xyzw_from_R(T_a_from_b[:3, :3])
    return kapture.PoseTransform(r=[q[3], q[0], q[1], q[2]], t=T_a_from_b[:3, 3].tolist())


def _observations(data, root: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """image name -> (keypoints (N, 2) in kapture pixels, points (N, 3)) from the
    reconstruction, for the first keypoints type with observations."""
    from kapture.io.features import get_keypoints_fullpath, image_keypoints_from_file

    if not data.observations or data.points3d is None or not data.keypoints:
        return {}
    points = np.asarray(data.points3d)[:, :3]
    for kp_type, keypoints in data.keypoints.items():
        per_image: dict[str, list[tuple[int, int]]] = {}
        for point_id, types in data.observations.items():
            for name, kp_index in types.get(kp_type, []):
                per_image.setdefault(name, []).append((kp_index, point_id))
        if not per_image:
            continue
        out = {}
        for name, pairs in per_image.items():
            path = get_keypoints_fullpath(kp_type, str(root), name)
            try:
                kps = image_keypoints_from_file(path, keypoints.dtype, keypoints.dsize)
            except (OSError, ValueError) as exc:
                raise InputFileError(Path(path), f"unreadable keypoints: {exc}") from exc
            pairs.sort()  # the image's keypoint order, not the points'
            index = np.array([k for k, _ in pairs], dtype=np.int64)
            ids = np.array([p for _, p in pairs], dtype=np.int64)
            if index.max() >= len(kps) or ids.max() >= len(points):
                raise InputFileError(Path(path), "observation beyond the keypoints or points")
            out[name] = (np.asarray(kps[index, :2], dtype=np.float64), points[ids])
        return out
    return {}


def _flat_poses(data, kapture):
    if data.trajectories is None:
        return {}
    trajectories = data.trajectories
    if data.rigs:
        trajectories = kapture.rigs_remove(trajectories, data.rigs)
    poses = {}
    for ts, sensor, pose in kapture.flatten(trajectories):
        T_sensor_from_world = _matrix(pose)
        if T_sensor_from_world is not None:
            poses[ts, sensor] = invert_rigid(T_sensor_from_world)
    return poses


def read_kapture(root: Path) -> PosedImages:
    """Open a kapture dataset folder (module doc). Raises InputFileError/InvalidInputError."""
    kapture = _import_kapture()
    from kapture.io.csv import kapture_from_dir
    from kapture.io.records import get_depth_map_fullpath, get_image_fullpath, get_record_fullpath

    root = Path(root).expanduser()
    if not (root / "sensors" / "sensors.txt").is_file():
        raise InputFileError(root, "not a kapture dataset (no sensors/sensors.txt)")
    try:
        data = kapture_from_dir(str(root))
    except Exception as exc:  # kapture raises plain ValueError/AssertionError/KeyError
        raise InputFileError(root, f"unreadable kapture dataset: {exc}") from exc
    sensors = data.sensors or {}
    poses = _flat_poses(data, kapture)
    observed = _observations(data, root)
    depth_by_ts: dict[int, list[str]] = {}
    for ts, sensor, _ in kapture.flatten(data.records_depth or {}):
        depth_by_ts.setdefault(ts, []).append(sensor)
    lidar_by_ts: dict[int, list[tuple[str, str]]] = {}
    for ts, sensor, name in kapture.flatten(data.records_lidar or {}):
        lidar_by_ts.setdefault(ts, []).append((sensor, name))
    images, skipped = [], {}

    def skip(reason: str) -> None:
        skipped[reason] = skipped.get(reason, 0) + 1

    for ts, sensor_id, name in kapture.flatten(data.records_camera or {}, is_sorted=True):
        sensor = sensors.get(sensor_id)
        if sensor is None:
            raise InputFileError(root / "sensors" / "sensors.txt", f"no sensor {sensor_id!r}")
        intrinsics = _intrinsics(sensor, str(root))
        T_world_from_cam = poses.get((ts, sensor_id))
        if T_world_from_cam is None:
            skip("no_pose")
            continue
        depth = lidar = None
        for depth_id in depth_by_ts.get(ts, []):
            if depth_id not in sensors:
                continue
            depth_pose = poses.get((ts, depth_id))
            registered = depth_pose is None or np.allclose(depth_pose, T_world_from_cam, atol=1e-3)
            if registered and _intrinsics(sensors[depth_id], str(root)) == intrinsics:
                depth_name = data.records_depth[ts, depth_id]
                size = (intrinsics.width_px, intrinsics.height_px)
                depth = DepthMapFile(Path(get_depth_map_fullpath(str(root), depth_name)), size)
                break
        if depth is None:
            for lidar_id, lidar_name in lidar_by_ts.get(ts, []):
                T_world_from_lidar = poses.get((ts, lidar_id))
                if T_world_from_lidar is not None:
                    T = invert_rigid(T_world_from_cam) @ T_world_from_lidar
                    lidar = LidarFile(Path(get_record_fullpath(str(root), lidar_name)), T)
                    break
        keypoints, points = observed.get(name, (np.zeros((0, 2)), np.zeros((0, 3))))
        if depth is None and lidar is None and len(keypoints) == 0:
            skip("no_3d_source")
            continue
        images.append(
            PosedImage(
                name=name,
                image_path=Path(get_image_fullpath(str(root), name)),
                intrinsics=intrinsics,
                T_model_from_cam=T_world_from_cam,
                timestamp_s=None,
                keypoints_px=keypoints - PIXEL_SHIFT,
                points_model=points,
                depth=depth,
                lidar=lidar,
            )
        )
    if not images and not skipped:
        raise InputFileError(root, "the kapture dataset has no camera record")
    return PosedImages(str(root), images, skipped, default_up=read_marker_up(root) or "z")


def _camera_sensor(kapture, c: CameraIntrinsics, name: str = CAMERA_ID):
    model, params = camera_model_of(c)
    return kapture.Camera(kapture.CameraType[model], [c.width_px, c.height_px, *params], name=name)


def write_kapture_map(views: list[ModelView], out_dir: Path, marker: dict | None = None) -> Path:
    """Write a map's entries (views with descriptors; ``record`` is the timestamp) as a
    kapture dataset in ``out_dir`` (module doc): one camera sensor per distinct
    intrinsics (``cam0``, ``cam1``, ...), the views' image files (if given) under
    ``sensors/records_data``, shared points as multi-view observations."""
    kapture = _import_kapture()
    from kapture.io.csv import kapture_to_dir
    from kapture.io.features import (
        get_descriptors_fullpath,
        get_keypoints_fullpath,
        image_descriptors_to_file,
        image_keypoints_to_file,
    )
    from kapture.io.records import get_image_fullpath

    out_dir = Path(out_dir).expanduser()
    out_dir.mkdir(parents=True, exist_ok=True)
    sensors = kapture.Sensors()
    sensor_of: dict[CameraIntrinsics, str] = {}
    for view in views:
        if view.intrinsics not in sensor_of:
            sensor_id = f"cam{len(sensor_of)}"
            sensor_of[view.intrinsics] = sensor_id
            sensors[sensor_id] = _camera_sensor(kapture, view.intrinsics, sensor_id)
    trajectories, records = kapture.Trajectories(), kapture.RecordsCamera()
    keypoints = kapture.Keypoints(FEATURE_TYPE, np.float32, 2)
    descriptor_set = kapture.Descriptors(FEATURE_TYPE, np.uint8, 32, FEATURE_TYPE, "Hamming")
    observations = kapture.Observations()
    points, point_index = tracks_of(views)
    for view, index in zip(views, point_index, strict=True):
        ts, desc = view.record, view.descriptors
        sensor_id = sensor_of[view.intrinsics]
        if desc is None or len(desc) != len(view.keypoints_px):
            raise InvalidInputError(f"{view.name}: one descriptor per keypoint is needed")
        trajectories[int(ts), sensor_id] = _pose(invert_rigid(view.T_world_from_cam))
        records[int(ts), sensor_id] = view.name
        keypoints.add(view.name)
        descriptor_set.add(view.name)
        kps = (np.asarray(view.keypoints_px, dtype=np.float32) + PIXEL_SHIFT).reshape(-1, 2)
        image_keypoints_to_file(get_keypoints_fullpath(FEATURE_TYPE, str(out_dir), view.name), kps)
        image_descriptors_to_file(
            get_descriptors_fullpath(FEATURE_TYPE, str(out_dir), view.name),
            np.ascontiguousarray(desc, dtype=np.uint8),
        )
        for k, point in enumerate(index.tolist()):
            observations.add(point, FEATURE_TYPE, view.name, k)
        if view.image_bytes is not None:
            target = Path(get_image_fullpath(str(out_dir), view.name))
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(view.image_bytes)
    data = kapture.Kapture(
        sensors=sensors,
        trajectories=trajectories,
        records_camera=records,
        keypoints={FEATURE_TYPE: keypoints},
        descriptors={FEATURE_TYPE: descriptor_set},
        points3d=kapture.Points3d(points, size=3) if len(points) else None,
        observations=observations if len(points) else None,
    )
    kapture_to_dir(str(out_dir), data)
    if marker is not None:
        (out_dir / MARKER_FILE).write_text(json.dumps(marker, indent=2) + "\n")
    return out_dir


def write_kapture_trajectory(
    timestamps_s: np.ndarray,
    T_world_from_cam: np.ndarray,
    out_dir: Path,
    camera: CameraIntrinsics | None = None,
    marker: dict | None = None,
) -> Path:
    """A trajectory (N,) timestamps and (N, 4, 4) poses as kapture ``trajectories.txt``
    of device ``cam0`` (microsecond timestamps), declared in ``sensors.txt`` with its
    intrinsics if known, else as kapture's ``UNKNOWN_CAMERA``."""
    kapture = _import_kapture()
    from kapture.io.csv import kapture_to_dir

    out_dir = Path(out_dir).expanduser()
    out_dir.mkdir(parents=True, exist_ok=True)
    trajectories = kapture.Trajectories()
    stamps_us = np.rint(np.asarray(timestamps_s, dtype=np.float64) * 1e6).astype(np.int64)
    if len(np.unique(stamps_us)) != len(stamps_us):
        raise InvalidInputError("the trajectory has two poses at the same microsecond")
    for ts, T in zip(stamps_us, T_world_from_cam, strict=True):
        trajectories[int(ts), CAMERA_ID] = _pose(invert_rigid(T))
    sensors = kapture.Sensors()
    if camera is not None:
        sensors[CAMERA_ID] = _camera_sensor(kapture, camera)
    else:  # kapture reads only the poses of declared devices
        sensors[CAMERA_ID] = kapture.Camera(kapture.CameraType.UNKNOWN_CAMERA, [0, 0], CAMERA_ID)
    kapture_to_dir(str(out_dir), kapture.Kapture(sensors=sensors, trajectories=trajectories))
    if marker is not None:
        (out_dir / MARKER_FILE).write_text(json.dumps(marker, indent=2) + "\n")
    return out_dir

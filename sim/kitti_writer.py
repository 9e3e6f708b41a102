"""The sim's writers of the KITTI odometry layout: the files' contents are
``monoloc.core.formats.kitti`` (calib, poses, times, velodyne scans, the layout's paths)
and ``monoloc.core.formats.vehicle``; here the images (OpenCV) and dataset.json.

<root>/sequences/NN/image_0/%06d.png   uint8 gray
<root>/sequences/NN/image_1/%06d.png   optional: uint8 gray, the right camera (P1)
<root>/sequences/NN/velodyne/%06d.bin  float32 (x, y, z, reflectance), LiDAR frame
<root>/sequences/NN/depth/%06d.png     optional: uint16 z-depth * 256, 0 = none
                                       (KITTI depth-benchmark encoding)
<root>/sequences/NN/calib.txt          P0..P3 (3x4), Tr (3x4, velodyne -> cam 0)
<root>/sequences/NN/times.txt          one time in seconds per frame
<root>/sequences/NN/vehicle.txt        t speed_mps yaw_rate_radps (measured)
<root>/sequences/NN/camera.json        a run whose camera is not the mapping camera's (the
                                       fleet run): fx fy cx cy width height distortion_model
                                       D (ROS CameraInfo's names and D order), K beside P0
<root>/sequences/NN/camera.yaml        the same camera in ROS's calibration layout, with
                                       T_vehicle_from_cam
<root>/poses/NN.txt                    3x4 T_world_from_cam0 row-major per line
<root>/dataset.json                    what each sequence is (see monoloc.sim.generate)
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.core.formats import kitti, vehicle
from monoloc.core.formats.camera_yaml import CAMERA_YAML, write_camera_yaml


def write_calib(
    path: Path,
    K: np.ndarray,
    T_cam_from_lidar: np.ndarray,
    stereo_baseline_m: float = kitti.KITTI_STEREO_BASELINE_M,
) -> None:
    """calib.txt (``KittiCalib.from_camera``): ``P0: 12 numbers`` ... ``P3:``, ``Tr:``."""
    with open(path, "w") as handle:
        kitti.write_calib(
            handle, kitti.KittiCalib.from_camera(K, T_cam_from_lidar, stereo_baseline_m)
        )


def write_poses(path: Path, T_world_from_cam: np.ndarray) -> None:
    """(n, 4, 4) poses -> one line of 12 numbers (3x4 row-major) per frame."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as handle:
        kitti.write_poses(handle, T_world_from_cam)


def write_times(path: Path, times_s: np.ndarray) -> None:
    with open(path, "w") as handle:
        kitti.write_times(handle, times_s)


def write_vehicle(
    path: Path, times_s: np.ndarray, speed_mps: np.ndarray, yaw_rate_radps: np.ndarray
) -> None:
    """vehicle.txt: ``t speed_mps yaw_rate_radps`` per frame."""
    with open(path, "w") as handle:
        vehicle.write_vehicle(handle, times_s, speed_mps, yaw_rate_radps)


def write_image(path: Path, image: np.ndarray) -> None:
    import cv2

    if not cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 3]):
        raise InvalidInputError(f"could not write {path}")


def write_depth(path: Path, depth_m: np.ndarray) -> None:
    """z-depth as uint16 PNG, value = round(depth * 256), 0 where no surface or beyond
    255.99 m (KITTI depth-benchmark encoding)."""
    import cv2

    d = np.where(np.isfinite(depth_m) & (depth_m < 255.99), depth_m * 256.0 + 0.5, 0.0)
    cv2.imwrite(str(path), d.astype(np.uint16), [cv2.IMWRITE_PNG_COMPRESSION, 3])


def read_depth(path: Path) -> np.ndarray:
    """Depth PNG -> (H, W) float32 metres, inf where none."""
    import cv2

    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise InvalidInputError(f"could not read depth image {path}")
    return np.where(raw > 0, raw.astype(np.float32) / 256.0, np.inf).astype(np.float32)


def write_camera_json(
    path: Path, intrinsics: CameraIntrinsics, T_vehicle_from_cam: np.ndarray | None = None
) -> None:
    """camera.json of a run's own camera: fx, fy, cx, cy, width, height (pixels),
    distortion_model ("none" for a pinhole) and D, the 3x3 K, and where the camera sits
    on the vehicle (``T_vehicle_from_cam``, 4x4, vehicle x forward, y left, z up); and
    camera.yaml beside it, the same in ROS's calibration layout
    (monoloc.core.formats.camera_yaml)."""
    k, lens = intrinsics, intrinsics.distortion
    info = {
        "fx": k.fx,
        "fy": k.fy,
        "cx": k.cx,
        "cy": k.cy,
        "width": k.width_px,
        "height": k.height_px,
        "distortion_model": "none" if lens is None else lens.model,
        "D": [] if lens is None else list(lens.coefficients),
        "K": k.K.tolist(),
    }
    if T_vehicle_from_cam is not None:
        info["T_vehicle_from_cam"] = np.asarray(T_vehicle_from_cam, dtype=float).tolist()
    Path(path).write_text(json.dumps(info, indent=2) + "\n")
    # the same camera in ROS's calibration layout, as a vehicle's recording carries it
    write_camera_yaml(Path(path).with_name(CAMERA_YAML), intrinsics, T_vehicle_from_cam, "fleet")


def write_dataset_json(root: Path, info: dict) -> None:
    (Path(root) / "dataset.json").write_text(json.dumps(info, indent=2) + "\n")

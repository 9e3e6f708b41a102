"""Fixtures of the ingestion tests.

- ``kitti_root``: a hand-made KITTI odometry sequence with known geometry: a wall of
  real photographs (scikit-image) on the plane z = 8 m of KITTI's world, seen by a
  camera that slides sideways (and yaws a little), with a LiDAR scan of the wall written
  through a KITTI-like velodyne-to-camera transform. Written once per session; tests
  that damage it work on ``kitti_copy``.
- ``tum_run``: the same wall as a TUM RGB-D run (depth images; frame 0 without ground
  truth, frame 7 without depth).
- ``factory``: a migrated SQLite file in tmp_path; ``make_map`` / ``make_run`` create
  an empty map (default vocabulary) and a run.

The sim-city tests (retrieval recall, hypothesis accuracy) are in
tests/server/test_localize_sim.py.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.geometry import invert_rigid

CAMERA = CameraIntrinsics(359.428, 359.428, 303.3464, 92.35785, 620, 188)
WALL_Z_M = 8.0  # the wall is the plane z = 8 m of KITTI's world (first camera frame)
TEXEL_M = 0.02
TEXTURE_ORIGIN_M = (-8.0, -3.0)  # KITTI world (x, y) of texel (0, 0)
STEP_M = 0.5
# velodyne -> camera like KITTI's: x_velo forward = z_cam, y_velo left = -x_cam,
# z_velo up = -y_cam, with a small offset.
T_CAM_FROM_LIDAR = np.array(
    [[0.0, -1.0, 0.0, 0.01], [0.0, 0.0, -1.0, -0.08], [1.0, 0.0, 0.0, -0.27], [0, 0, 0, 1.0]]
)


@dataclass(frozen=True)
class KittiFixture:
    root: Path  # dataset root (sequences/00, poses/00.txt)
    T_kitti_from_cam: np.ndarray  # (n, 4, 4) true poses in KITTI's world
    camera: CameraIntrinsics = CAMERA
    T_cam_from_lidar: np.ndarray = field(default_factory=T_CAM_FROM_LIDAR.copy)
    wall_z_m: float = WALL_Z_M

    @property
    def sequence_dir(self) -> Path:
        return self.root / "sequences" / "00"


def wall_texture(width_texels: int, height_texels: int = 320) -> np.ndarray:
    """Gray photographs side by side, so every part of the wall looks different."""
    import cv2
    from skimage import data

    photos = [
        data.astronaut(),
        data.camera(),
        data.coffee(),
        data.chelsea(),
        data.brick(),
        data.text(),
        data.rocket(),
        data.page(),
    ]
    strips, width = [], 0
    while width < width_texels:
        photo = photos[len(strips) % len(photos)]
        gray = cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY) if photo.ndim == 3 else photo
        scale = height_texels / gray.shape[0]
        strips.append(
            cv2.resize(
                gray, (int(gray.shape[1] * scale), height_texels), interpolation=cv2.INTER_AREA
            )
        )
        width += strips[-1].shape[1]
    return np.ascontiguousarray(np.concatenate(strips, axis=1)[:, :width_texels])


def render_wall(texture: np.ndarray, T_kitti_from_cam: np.ndarray) -> np.ndarray:
    """The camera's view of the wall (a homography of the texture)."""
    import cv2

    R, c = T_kitti_from_cam[:3, :3], T_kitti_from_cam[:3, 3]
    x0, y0 = TEXTURE_ORIGIN_M
    plane = np.column_stack([[TEXEL_M, 0, 0], [0, TEXEL_M, 0], np.array([x0, y0, WALL_Z_M]) - c])
    H = CAMERA.K @ R.T @ plane
    return cv2.warpPerspective(
        texture, H, (CAMERA.width_px, CAMERA.height_px), flags=cv2.INTER_LINEAR, borderValue=90
    )


def wall_scan(T_kitti_from_cam: np.ndarray) -> np.ndarray:
    """(N, 4) float32 LiDAR points (x, y, z, r) of the wall around the camera."""
    c = T_kitti_from_cam[:3, 3]
    xs = np.arange(c[0] - 9.0, c[0] + 9.0, 0.04)
    ys = np.arange(-2.9, 3.3, 0.04)
    gx, gy = np.meshgrid(xs, ys)
    world = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, WALL_Z_M), np.ones(gx.size)])
    T_lidar_from_world = invert_rigid(T_CAM_FROM_LIDAR) @ invert_rigid(T_kitti_from_cam)
    points = (world @ T_lidar_from_world.T)[:, :3]
    return np.column_stack([points, np.full(len(points), 0.5)]).astype(np.float32)


def _row(values) -> str:
    return " ".join(f"{v:.12e}" for v in np.asarray(values, dtype=np.float64).ravel())


def write_kitti_fixture(root: Path, n_frames: int = 8) -> KittiFixture:
    """Write the hand-made sequence 00 under ``root`` (see the module docstring)."""
    import cv2

    seq = root / "sequences" / "00"
    (seq / "image_0").mkdir(parents=True)
    (seq / "velodyne").mkdir()
    (root / "poses").mkdir()
    P0 = np.column_stack([CAMERA.K, np.zeros(3)])
    (seq / "calib.txt").write_text(
        "".join(f"P{i}: {_row(P0)}\n" for i in range(4)) + f"Tr: {_row(T_CAM_FROM_LIDAR[:3])}\n"
    )
    texture = wall_texture(int((16.0 + STEP_M * n_frames) / TEXEL_M) + 10)
    poses = []
    for i in range(n_frames):
        yaw = 0.03 * ((i % 3) - 1)  # about KITTI's vertical (y) axis
        T = np.eye(4)
        T[:3, :3] = [[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]]
        T[:3, 3] = [STEP_M * i, 0.05 * np.sin(i), 0.1 * i]
        poses.append(T)
        cv2.imwrite(str(seq / "image_0" / f"{i:06d}.png"), render_wall(texture, T))
        wall_scan(T).tofile(seq / "velodyne" / f"{i:06d}.bin")
    poses = np.stack(poses)
    (root / "poses" / "00.txt").write_text("".join(_row(T[:3]) + "\n" for T in poses))
    (seq / "times.txt").write_text("".join(f"{0.1 * i:e}\n" for i in range(n_frames)))
    return KittiFixture(root, poses)


@pytest.fixture(scope="session")
def kitti_root(tmp_path_factory) -> KittiFixture:
    """The hand-made sequence (read-only: copy it with ``kitti_copy`` to damage it)."""
    return write_kitti_fixture(tmp_path_factory.mktemp("kitti"))


@pytest.fixture
def kitti_copy(kitti_root: KittiFixture, tmp_path: Path) -> KittiFixture:
    root = tmp_path / "kitti_copy"
    shutil.copytree(kitti_root.root, root)
    return KittiFixture(root, kitti_root.T_kitti_from_cam)


def new_map(factory, camera: CameraIntrinsics = CAMERA, name: str = "m") -> int:
    """An empty map with the default vocabulary; returns its id."""
    from monoloc.server.ingest.manage import create_map

    return create_map(factory, name, camera).id


def new_run(factory, map_id: int, source, kind: str = "map") -> int:
    from monoloc.server.storage import runs as runs_repo
    from monoloc.server.storage.db import session_scope

    with session_scope(factory) as session:
        return runs_repo.create_run(
            session, map_id, kind=kind, source_format=source.format, source_name=source.name
        ).id


@pytest.fixture
def make_map(factory):
    """make_map(camera=CAMERA, name="m") -> id of a new empty map (default vocabulary)."""
    return lambda camera=CAMERA, name="m": new_map(factory, camera, name)


@pytest.fixture
def make_run(factory):
    """make_run(map_id, source, kind="map") -> id of a new run of that source."""
    return lambda map_id, source, kind="map": new_run(factory, map_id, source, kind)


@pytest.fixture
def tum_run(tmp_path, kitti_root):
    """8 frames of the wall; frame 0 has no ground truth, frame 7 no depth partner."""
    import cv2

    from monoloc.core.geometry import kitti_to_zup, quaternion_xyzw_from_R

    root = tmp_path / "tum"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    cam = kitti_root.camera
    rgb_lines, depth_lines, gt_lines = ["# rgb"], ["# depth"], ["# ground truth"]
    for i, T_kitti in enumerate(kitti_root.T_kitti_from_cam):
        t = 10.0 + 0.1 * i
        gray = cv2.imread(str(kitti_root.sequence_dir / "image_0" / f"{i:06d}.png"), 0)
        colour = cv2.merge([gray, gray, gray])
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), colour)
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        # Depth of the wall z = 8 (KITTI world) along each pixel's ray.
        K_inv = np.linalg.inv(cam.K)
        u, v = np.meshgrid(np.arange(cam.width_px), np.arange(cam.height_px))
        rays = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3) @ K_inv.T
        rays_world = rays @ T_kitti[:3, :3].T
        z = (kitti_root.wall_z_m - T_kitti[2, 3]) / rays_world[:, 2]  # camera z = ray scale
        depth = np.round(z * 5000).astype(np.uint16).reshape(cam.height_px, cam.width_px)
        if i != 7:
            cv2.imwrite(str(root / "depth" / f"{t + 0.004:.6f}.png"), depth)
            depth_lines.append(f"{t + 0.004:.6f} depth/{t + 0.004:.6f}.png")
        T_zup = kitti_to_zup(T_kitti)
        if i > 0:
            q = quaternion_xyzw_from_R(T_zup[:3, :3])
            gt_lines.append(f"{t:.4f} " + " ".join(f"{x:.9f}" for x in (*T_zup[:3, 3], *q)))
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    intrinsics = {
        "fx": cam.fx,
        "fy": cam.fy,
        "cx": cam.cx,
        "cy": cam.cy,
        "width": cam.width_px,
        "height": cam.height_px,
        "depth_scale": 5000,
    }
    (root / "intrinsics.json").write_text(json.dumps(intrinsics))
    return root

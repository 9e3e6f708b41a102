import numpy as np

from monoloc.core.camera import KITTI_CAM0
from monoloc.server.vision.depth import (
    DepthAssociationConfig,
    points_from_depth_image,
    points_from_lidar,
    project_points,
)

# KITTI-like LiDAR mount: x forward, y left, z up; 0.27 m behind and 0.08 m above cam0.
T_CAM_FROM_LIDAR = np.array(
    [[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, -0.08], [1.0, 0.0, 0.0, -0.27], [0, 0, 0, 1.0]]
)


def _ring_scan(depth_of_ray, n_rings=64, n_azimuth=2000):
    """A spinning LiDAR (+2 .. -24.8 deg) whose rays hit at range depth_of_ray(dirs)."""
    elev = np.radians(np.linspace(2.0, -24.8, n_rings))
    azim = np.radians(np.linspace(-60, 60, n_azimuth))
    e, a = np.meshgrid(elev, azim, indexing="ij")
    dirs = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    rng = depth_of_ray(dirs)
    return dirs * rng[:, None]


def test_lidar_points_on_a_wall_give_true_depth_and_reproject():
    # A wall 12 m ahead of the LiDAR: x_lidar = 12.
    scan = _ring_scan(lambda d: 12.0 / d[:, 0])
    rng = np.random.default_rng(0)
    kp = np.stack([rng.uniform(100, 1100, 300), rng.uniform(200, 370, 300)], 1).astype(np.float32)
    pts, has = points_from_lidar(kp, scan, T_CAM_FROM_LIDAR, KITTI_CAM0)
    assert has.mean() > 0.9
    # Camera is 0.27 m in front of the LiDAR: the wall is 11.73 m from the camera.
    assert np.allclose(pts[has, 2], 11.73, atol=0.02)
    assert np.allclose(project_points(pts[has], KITTI_CAM0), kp[has], atol=1e-3)


def test_keypoints_on_a_depth_edge_are_dropped():
    # Near box (5 m) for lateral angle > 0 (left), far wall (30 m) elsewhere.
    def hit(d):
        near = d[:, 1] > 0
        return np.where(near, 5.0 / d[:, 0], 30.0 / d[:, 0])

    scan = _ring_scan(hit)
    # Image column of the edge: straight ahead of the LiDAR, shifted by the mount.
    edge_u = KITTI_CAM0.cx
    kp = np.array([[edge_u, 260.0], [edge_u - 200, 260.0], [edge_u + 200, 260.0]], np.float32)
    _, has = points_from_lidar(kp, scan, T_CAM_FROM_LIDAR, KITTI_CAM0)
    assert has.tolist() == [False, True, True]


def test_depth_image_lookup_with_scale_and_invalid_pixels():
    depth_raw = np.full((376, 1241), 5000 * 7, dtype=np.uint16)  # 7 m everywhere
    depth_raw[:, :100] = 0  # no return on the left
    depth_raw[200:, 600:700] = 5000 * 3  # a step
    kp = np.array([[50.0, 50.0], [300.0, 100.0], [600.0, 200.0], [650.0, 300.0]], np.float32)
    pts, has = points_from_depth_image(kp, depth_raw, 5000.0, KITTI_CAM0)
    assert has.tolist() == [False, True, False, True]
    assert np.allclose(pts[1, 2], 7.0) and np.allclose(pts[3, 2], 3.0)
    strict = DepthAssociationConfig(min_points=20)
    _, has = points_from_depth_image(kp, depth_raw, 5000.0, KITTI_CAM0, strict)
    assert not has.any()

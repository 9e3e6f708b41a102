import numpy as np
import pytest

from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import (
    R_from_quaternion_xyzw,
    T_world_from_cam_planar,
    check_rigid,
    circular_mean,
    invert_rigid,
    kitti_to_zup,
    planar_from_T_world_from_cam,
    quaternion_xyzw_from_R,
    wrap_angle,
    zup_to_kitti,
)


def test_wrap_angle_range_and_edges():
    angles = np.linspace(-20, 20, 1001)
    wrapped = wrap_angle(angles)
    assert np.all(wrapped > -np.pi) and np.all(wrapped <= np.pi)
    assert np.allclose(np.cos(wrapped), np.cos(angles)) and np.allclose(
        np.sin(wrapped), np.sin(angles)
    )
    assert wrap_angle(-np.pi) == pytest.approx(np.pi)
    assert wrap_angle(3 * np.pi) == pytest.approx(np.pi)


def test_planar_pose_round_trip_with_tilt():
    rng = np.random.default_rng(0)
    for _ in range(50):
        x, y, yaw = rng.uniform(-100, 100), rng.uniform(-100, 100), rng.uniform(-np.pi, np.pi)
        T = T_world_from_cam_planar(x, y, yaw, height_m=1.65, pitch_rad=0.05, roll_rad=-0.02)
        check_rigid(T)
        assert np.allclose(planar_from_T_world_from_cam(T), [x, y, yaw], atol=1e-9)


def test_level_camera_axes():
    T = T_world_from_cam_planar(0, 0, np.pi / 2)
    # Optical axis points to +Y, image right to +X, image down to -Z.
    assert np.allclose(T[:3, 2], [0, 1, 0])
    assert np.allclose(T[:3, 0], [1, 0, 0])
    assert np.allclose(T[:3, 1], [0, 0, -1])
    # Positive pitch looks up.
    T_up = T_world_from_cam_planar(0, 0, 0.0, pitch_rad=0.1)
    assert T_up[2, 2] > 0


def test_kitti_first_frame_is_origin_facing_plus_x():
    T_zup = kitti_to_zup(np.eye(4))
    assert np.allclose(planar_from_T_world_from_cam(T_zup), [0, 0, 0])
    # KITTI camera moving forward (z) 10 m -> +X in the z-up world.
    T_k = np.eye(4)
    T_k[2, 3] = 10.0
    assert np.allclose(kitti_to_zup(T_k)[:3, 3], [10, 0, 0])
    assert np.allclose(zup_to_kitti(kitti_to_zup(T_k)), T_k)


def test_invert_and_quaternion_round_trip():
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = rng.normal(size=4)
        R = R_from_quaternion_xyzw(q)
        q2 = quaternion_xyzw_from_R(R)
        assert np.allclose(R_from_quaternion_xyzw(q2), R, atol=1e-9)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = rng.normal(size=3)
        assert np.allclose(invert_rigid(T) @ T, np.eye(4), atol=1e-12)


def test_check_rigid_rejects_bad_matrices():
    with pytest.raises(InvalidInputError):
        check_rigid(np.eye(3))
    bad = np.eye(4)
    bad[0, 0] = np.nan
    with pytest.raises(InvalidInputError):
        check_rigid(bad)
    scaled = np.eye(4)
    scaled[:3, :3] *= 2
    with pytest.raises(InvalidInputError):
        check_rigid(scaled)


def test_circular_mean_across_the_seam():
    assert abs(wrap_angle(circular_mean(np.array([np.pi - 0.1, -np.pi + 0.1])) - np.pi)) < 1e-9

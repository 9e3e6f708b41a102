"""T_vehicle_from_cam by its parts (monoloc.core.mounting): the parts and the matrix go
round trip, the planar mount agrees with the full 3D transform, and the motion model's
step with a mounting is the vehicle's arc seen through it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from monoloc.client.motion import advance
from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import planar_from_T_world_from_cam, wrap_angle
from monoloc.core.mounting import CameraMounting, PlanarMount

MOUNT = CameraMounting(
    lever_arm_m=1.4, lateral_m=-0.3, height_m=1.42, roll_rad=0.01, pitch_rad=0.052, yaw_rad=0.014
)


def _T_world_from_vehicle(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    T[:3, 3] = [x, y, z]
    return T


def test_the_parts_and_the_matrix_go_round_trip():
    T = MOUNT.T_vehicle_from_cam
    back = CameraMounting.from_T_vehicle_from_cam(T)
    for name, value in MOUNT.to_dict().items():
        assert getattr(back, name) == pytest.approx(value, abs=1e-12), name
    # looking straight ahead, level: the optical axis is the vehicle's x, image x its -y
    R = CameraMounting().R_vehicle_from_cam
    np.testing.assert_allclose(R @ [0, 0, 1], [1, 0, 0])
    np.testing.assert_allclose(R @ [1, 0, 0], [0, -1, 0])
    np.testing.assert_allclose(R @ [0, 1, 0], [0, 0, -1])
    # positive pitch looks down, positive yaw looks left
    axis = CameraMounting(pitch_rad=0.1).R_vehicle_from_cam @ [0, 0, 1]
    assert axis[2] < 0
    assert (CameraMounting(yaw_rad=0.1).R_vehicle_from_cam @ [0, 0, 1])[1] > 0
    assert CameraMounting.from_dict({"T_vehicle_from_cam": T.tolist()}) == back
    assert CameraMounting.from_dict({"T_vehicle_from_cam": {"rows": 4, "data": T.ravel().tolist()}})
    assert CameraMounting.from_dict({"height_m": 1.2}).height_m == 1.2
    with pytest.raises(InvalidInputError, match="unknown mounting field"):
        CameraMounting.from_dict({"heigth_m": 1.2})
    with pytest.raises(InvalidInputError, match="not a rigid transform"):
        CameraMounting.from_T_vehicle_from_cam(np.diag([2.0, 1.0, 1.0, 1.0]))


def test_the_planar_mount_is_the_3d_transform_on_the_ground():
    rng = np.random.default_rng(3)
    mount = MOUNT.planar
    for _ in range(20):
        x, y, yaw = rng.uniform(-50, 50), rng.uniform(-50, 50), rng.uniform(-math.pi, math.pi)
        T_world_from_cam = _T_world_from_vehicle(x, y, yaw) @ MOUNT.T_vehicle_from_cam
        camera = planar_from_T_world_from_cam(T_world_from_cam)
        np.testing.assert_allclose(mount.camera_from_vehicle([x, y, yaw]), camera, atol=1e-9)
        back = mount.vehicle_from_camera(camera)
        np.testing.assert_allclose(back[:2], [x, y], atol=1e-9)
        assert wrap_angle(back[2] - yaw) == pytest.approx(0.0, abs=1e-9)
        # the camera sits at height_m over the vehicle's ground point
        assert T_world_from_cam[2, 3] == pytest.approx(MOUNT.height_m)


def test_a_step_with_a_mounting_is_the_vehicles_arc_seen_through_it():
    mount = PlanarMount(1.4, -0.3, 0.05)
    vehicle = np.array([[2.0, -1.0, 0.3], [0.0, 0.0, -2.0]])
    speed, yaw_rate, dt = np.array([9.0, 4.0]), np.array([0.47, -0.2]), 0.1
    # the vehicle's reference point drives the exact arc along its heading
    turn = yaw_rate * dt
    radius = speed / yaw_rate
    moved = vehicle.copy()
    moved[:, 0] += radius * (np.sin(vehicle[:, 2] + turn) - np.sin(vehicle[:, 2]))
    moved[:, 1] += radius * (np.cos(vehicle[:, 2]) - np.cos(vehicle[:, 2] + turn))
    moved[:, 2] += turn
    camera = mount.camera_from_vehicle(vehicle)
    np.testing.assert_allclose(
        advance(camera, speed, yaw_rate, dt, mount), mount.camera_from_vehicle(moved), atol=1e-12
    )
    # a float is a lever arm: the old model's
    lever = PlanarMount(1.4)
    np.testing.assert_allclose(
        advance(lever.camera_from_vehicle(vehicle), speed, yaw_rate, dt, 1.4),
        lever.camera_from_vehicle(moved),
        atol=1e-12,
    )

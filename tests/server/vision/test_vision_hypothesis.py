import numpy as np
import pytest

from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import T_world_from_cam_planar
from monoloc.server.vision.hypothesis import compose_hypothesis, planar_hypothesis


def test_query_two_metres_ahead_and_turned_right():
    T_world_from_ref = T_world_from_cam_planar(10.0, 5.0, 0.3, height_m=1.65)
    turn = np.radians(10.0)
    T_ref_from_query = np.eye(4)
    # Rotation about the camera's y axis (down): the optical axis turns right, so the
    # heading (counter-clockwise from +X) decreases.
    T_ref_from_query[:3, :3] = [
        [np.cos(turn), 0, np.sin(turn)],
        [0, 1, 0],
        [-np.sin(turn), 0, np.cos(turn)],
    ]
    T_ref_from_query[:3, 3] = [0.0, 0.0, 2.0]
    T_world_from_query = compose_hypothesis(T_world_from_ref, T_ref_from_query)
    assert np.allclose(T_world_from_query, T_world_from_ref @ T_ref_from_query)
    assert T_world_from_query[2, 3] == pytest.approx(1.65)
    expected = [10.0 + 2 * np.cos(0.3), 5.0 + 2 * np.sin(0.3), 0.3 - turn]
    assert np.allclose(planar_hypothesis(T_world_from_ref, T_ref_from_query), expected)


def test_rejected_or_non_rigid_inputs_raise():
    T = T_world_from_cam_planar(0.0, 0.0, 0.0)
    with pytest.raises(InvalidInputError):
        compose_hypothesis(T, np.full((4, 4), np.nan))
    with pytest.raises(InvalidInputError):
        compose_hypothesis(2.0 * T, np.eye(4))

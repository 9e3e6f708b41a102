import io
import math

import numpy as np
import pytest

from monoloc.client.trajectory import poses_from_planar, trajectory_metrics, write_trajectory_files
from monoloc.core.errors import InvalidInputError
from monoloc.core.formats.kitti import write_poses
from monoloc.core.formats.tum import write_trajectory
from monoloc.core.geometry import kitti_to_zup, planar_from_T_world_from_cam, zup_to_kitti


def test_tum_and_kitti_round_trip_through_text():
    planar = np.array([[1.0, 2.0, 0.3], [4.0, -1.0, -2.9]])
    poses = poses_from_planar(planar, height_m=1.65)
    buf = io.StringIO()
    write_trajectory(buf, np.array([0.0, 0.1]), poses)
    rows = np.loadtxt(io.StringIO(buf.getvalue()))
    assert rows.shape == (2, 8)
    assert np.allclose(rows[:, 1:4], poses[:, :3, 3])
    assert np.allclose(np.linalg.norm(rows[:, 4:], axis=1), 1.0)
    buf = io.StringIO()
    write_poses(buf, zup_to_kitti(poses))
    kitti = np.loadtxt(io.StringIO(buf.getvalue())).reshape(-1, 3, 4)
    T = np.tile(np.eye(4), (2, 1, 1))
    T[:, :3, :] = kitti
    assert np.allclose(planar_from_T_world_from_cam(kitti_to_zup(T)), planar, atol=1e-6)


def test_trajectory_files_are_written(tmp_path):
    tum, kitti = write_trajectory_files(tmp_path / "out" / "run", [0.0], [[0.0, 0.0, 0.0]])
    assert tum.read_text().count("\n") == 1 and kitti.read_text().count("\n") == 1


def test_metrics_values_and_misses():
    truth = np.zeros((4, 3))
    est = np.array([[0.1, 0.0, 0.0], [0.0, 0.3, 0.0], [3.0, 4.0, math.radians(8)], [np.nan] * 3])
    m = trajectory_metrics(est, truth)
    assert m.n_frames == 4
    assert m.position_rmse_m == pytest.approx(math.sqrt((0.01 + 0.09 + 25) / 3))
    assert m.within_0_25m_2deg == pytest.approx(0.25)
    assert m.within_0_5m_5deg == pytest.approx(0.5)
    assert m.within_5m_10deg == pytest.approx(0.75)
    with pytest.raises(InvalidInputError):
        trajectory_metrics(est[:2], truth)


def test_truth_in_map_frame_carries_the_nearest_map_error():
    from monoloc.client.trajectory import truth_in_map_frame

    # A straight map along X whose written poses drift: +2 cm in Y per 10 m, +0.1 deg.
    x_m = np.arange(0.0, 50.0, 1.0)
    map_true = np.stack([x_m, np.zeros_like(x_m), np.zeros_like(x_m)], axis=1)
    map_written = map_true + np.stack(
        [np.zeros_like(x_m), 0.002 * x_m, np.full_like(x_m, math.radians(0.1))], axis=1
    )
    query_true = np.array([[10.2, 0.8, 0.05], [30.4, -1.0, math.pi - 0.001]])
    placed = truth_in_map_frame(query_true, map_true, map_written)
    np.testing.assert_allclose(placed[:, 0], query_true[:, 0])
    np.testing.assert_allclose(placed[:, 1], query_true[:, 1] + [0.02, 0.06])
    # the heading error is added and wrapped (pi - 0.001 + 0.1 deg crosses pi)
    np.testing.assert_allclose(placed[0, 2], 0.05 + math.radians(0.1))
    assert placed[1, 2] == pytest.approx(-math.pi - 0.001 + math.radians(0.1))
    with pytest.raises(InvalidInputError):
        truth_in_map_frame(query_true, map_true, map_written[:-1])

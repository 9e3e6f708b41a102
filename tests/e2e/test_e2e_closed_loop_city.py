"""The closed loop in the sim's city end to end: a short mapping drive along the lane
recorded by the sim's vehicle with camera + LiDAR in the KITTI layout, uploaded to a real
server through the HTTP API, then the car steering on monoloc's estimate over HTTP."""

from __future__ import annotations

import numpy as np
import pytest
from e2e_helpers import mapped_loop_server

from monoloc.core.formats import kitti as kitti_format
from monoloc.sim.closed_loop_metrics import loop_metrics
from monoloc.sim.closed_loop_study import (
    StudyConfig,
    drive_case,
)
from monoloc.sim.closed_loop_world import UrbanLoopWorld

MAP_FRAMES, DRIVE_FRAMES = 50, 30


@pytest.fixture(scope="module")
def city_map(tmp_path_factory):
    root = tmp_path_factory.mktemp("closed_loop_city")
    world = UrbanLoopWorld("small", seed=0)
    with mapped_loop_server(world, root, MAP_FRAMES, "city", 120.0) as (client, map_id, run, lap):
        yield client, map_id, world, run, lap


def test_the_city_mapping_drive_is_a_kitti_run_with_lidar(city_map):
    client, map_id, world, run_dir, lap = city_map
    seq = run_dir / "sequences" / "00"
    assert len(list((seq / "image_0").glob("*.png"))) == lap.n_frames
    assert len(list((seq / "velodyne").glob("*.bin"))) == lap.n_frames
    poses = kitti_format.read_poses(run_dir / "poses" / "00.txt")
    assert len(poses) == lap.n_frames
    calib = kitti_format.read_calib(seq / "calib.txt")
    np.testing.assert_allclose(calib.T_cam0_from_lidar, world.T_cam_from_lidar, atol=1e-6)
    info = client.request("GET", f"/v1/maps/{map_id}").json()
    assert 0.8 * lap.n_frames <= info["n_entries"] <= lap.n_frames


def test_the_car_steers_on_the_estimate_in_its_lane(city_map):
    client, map_id, world, _run_dir, _lap = city_map
    study = StudyConfig(laps=1.0, max_frames=DRIVE_FRAMES, seed=5, train_laps=0)
    # a recorded delay below the frame period: every frame is sent, whatever the host's load
    result = drive_case(client, map_id, world, "closed", study, (40.0,))
    m = loop_metrics(result, spike_threshold_m=0.5)
    assert result.n_frames == DRIVE_FRAMES and np.all(result.frames["sent"])
    believed = result.frames["believed_vehicle"]
    gap = np.linalg.norm(believed[:, :2] - result.frames["truth_vehicle"][:, :2], axis=1)
    assert np.max(gap) > 1e-4  # the controller acted on the estimate, not the truth
    assert m["lane_departures"] == 0 and m["lateral_max_m"] < world.lane_half_width_m
    assert m["hypotheses_share"] > 0.5 and m["estimated_share"] > 0.8
    assert m["loc_rmse_m"] < 0.3, m["loc_rmse_m"]

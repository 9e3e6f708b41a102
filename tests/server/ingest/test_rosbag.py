"""ROS 2 bags as mapping runs: bags written with rosbags' writer from a sim run are
ingested like the same run in KITTI layout (same entries, same poses), with a point cloud
or a depth image, poses from Odometry or /tf; bad bags fail with a message that names
the problem, and nothing is stored."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from rosbag_helpers import SimRun, write_sim_bag

from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import planar_from_T_world_from_cam
from monoloc.server.ingest.pipeline import ingest_run
from monoloc.server.ingest.sources import read_kitti_sequence, read_rosbag_run
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage.db import session_scope


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory) -> tuple[Path, SimRun]:
    """A 6-frame sim run (half-size images, LiDAR, depth) with exact recordings."""
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.lidar import LidarConfig
    from monoloc.sim.recording import RecordingErrors

    root = tmp_path_factory.mktemp("bag_sim")
    config = GenerateConfig(
        seed=3,
        runs=("map",),
        max_frames=6,
        image_scale=0.5,
        write_depth=True,
        errors=RecordingErrors.none(),
        lidar=LidarConfig(azimuth_steps=1000),
    )
    generate_dataset(config, root)
    return root, SimRun.read(root, "00")


def _entries(factory, map_id):
    with session_scope(factory) as session:
        return entries_repo.list_entries(session, map_id, limit=1000)


def _ingest(factory, make_map, make_run, source, name):
    map_id = make_map(source.intrinsics, name)
    summary = ingest_run(factory, map_id, source, run_id=make_run(map_id, source))
    return map_id, summary


def test_bag_with_point_cloud_gives_the_kitti_runs_entries(
    sim_run, tmp_path, factory, make_map, make_run
):
    root, run = sim_run
    bag = write_sim_bag(run, tmp_path / "drive_bag")
    source = read_rosbag_run(bag)
    assert source.topics == {
        "image": "/camera/image_raw",
        "camera_info": "/camera/camera_info",
        "cloud": "/velodyne_points",
        "pose": "/odom",
    }
    assert len(source.frames) == len(run.images) and not source.read_skips
    # Odometry of base_link + the static rig give back the camera's true poses
    T = np.stack([f.T_world_from_cam for f in source.frames])
    np.testing.assert_allclose(T, run.T_world_from_cam, atol=1e-9)
    np.testing.assert_allclose(source.T_cam_from_lidar, run.T_cam_from_lidar, atol=1e-9)

    kitti = read_kitti_sequence(root, "00")
    assert source.intrinsics == kitti.intrinsics
    bag_map, bag_summary = _ingest(factory, make_map, make_run, source, "bag")
    kitti_map, kitti_summary = _ingest(factory, make_map, make_run, kitti, "kitti")
    assert bag_summary.entries_added == kitti_summary.entries_added >= 4
    from_bag, from_kitti = _entries(factory, bag_map), _entries(factory, kitti_map)
    # the same pixels: the same content hash, poses and 3D keypoints
    assert [e.source_image_hash for e in from_bag] == [e.source_image_hash for e in from_kitti]
    assert [e.n_points for e in from_bag] == [e.n_points for e in from_kitti]
    for a, b in zip(from_bag, from_kitti, strict=True):
        assert (a.x_m, a.y_m, a.yaw_rad) == pytest.approx((b.x_m, b.y_m, b.yaw_rad), abs=1e-9)

    # idempotent: the same bag again adds nothing
    again = ingest_run(factory, bag_map, source, run_id=make_run(bag_map, source))
    assert again.entries_added == 0
    assert again.skip_reasons == {"already_in_map": bag_summary.entries_added}
    assert len(_entries(factory, bag_map)) == len(from_bag)


def test_bag_with_depth_images_png_frames_and_tf_poses(
    sim_run, tmp_path, factory, make_map, make_run
):
    _, run = sim_run
    bag = write_sim_bag(
        run, tmp_path / "depth_bag", image="compressed", three_d="depth", poses="tf"
    )
    source = read_rosbag_run(bag)
    assert source.topics["depth"] == "/camera/depth/image" and "pose" not in source.topics
    T = np.stack([f.T_world_from_cam for f in source.frames])
    np.testing.assert_allclose(T, run.T_world_from_cam, atol=1e-9)
    map_id, summary = _ingest(factory, make_map, make_run, source, "depth")
    assert summary.entries_added >= 4 and summary.points_min >= 20
    entries = _entries(factory, map_id)
    truth = planar_from_T_world_from_cam(run.T_world_from_cam)
    frame_of_time = {round(f.timestamp_s, 6): f.index for f in source.frames}
    assert len(entries) == summary.entries_added
    for entry in entries:  # every entry sits at its frame's true pose
        i = frame_of_time[round(entry.timestamp_s, 6)]
        assert (entry.x_m, entry.y_m, entry.yaw_rad) == pytest.approx(tuple(truth[i]), abs=1e-9)


def test_bad_bags_fail_clearly_and_store_nothing(sim_run, tmp_path, factory, make_map):
    _, run = sim_run
    no_poses = write_sim_bag(run, tmp_path / "no_poses", poses="none")
    with pytest.raises(InvalidInputError, match="moving transform"):
        read_rosbag_run(no_poses)
    no_3d = write_sim_bag(run, tmp_path / "no_3d", three_d="none")
    with pytest.raises(InvalidInputError, match="no 3D source"):
        read_rosbag_run(no_3d)
    with pytest.raises(InvalidInputError, match="unknown topic role"):
        read_rosbag_run(no_3d, topics={"lidar": "/velodyne_points"})
    with pytest.raises(InvalidInputError, match="no topic '/camera/left'"):
        read_rosbag_run(no_3d, topics={"image": "/camera/left"})
    with pytest.raises(InvalidInputError, match="is sensor_msgs/msg/CameraInfo, not a image"):
        read_rosbag_run(no_3d, topics={"image": "/camera/camera_info"})
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "metadata.yaml").write_text("not: a bag\n")
    with pytest.raises(InvalidInputError, match="not a readable ROS bag"):
        read_rosbag_run(tmp_path / "junk")
    map_id = make_map()
    assert _entries(factory, map_id) == []


def test_cli_ingests_a_bag_and_reports_a_bad_one_in_one_line(
    sim_run, tmp_path, monkeypatch, capsys
):
    from monoloc.cli import main

    _, run = sim_run
    bag = write_sim_bag(run, tmp_path / "cli_bag", image="compressed")
    monkeypatch.setenv("MONOLOC_DATA_DIR", str(tmp_path / "data"))

    def call(*args) -> int:
        monkeypatch.setattr(sys, "argv", ["monoloc", *args])
        try:
            main()
        except SystemExit as exc:
            return int(exc.code or 0)
        return 0

    camera = ["--fx", "359.428", "--fy", "359.428", "--cx", "303.3464", "--cy", "92.35785"]
    assert call("map", "create", "street", *camera, "--width", "620", "--height", "188") == 0
    ingest = ["map", "ingest", "--map", "street", "--format", "rosbag", str(bag)]
    code = call(*ingest, "--topic", "image=/camera/image_raw/compressed", "--topic", "pose=/odom")
    out = capsys.readouterr()
    assert code == 0, out.err
    assert "entries added" in out.out
    assert call(*ingest, "--topic", "x") == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "ROLE=TOPIC" in err and "\n" not in err
    assert call(*ingest, "--topic", "pose=/nowhere") == 1
    assert capsys.readouterr().err.strip() == (
        f"error: {bag}: no topic '/nowhere' (pose); topics: ['/camera/camera_info', "
        "'/camera/image_raw/compressed', '/odom', '/tf_static', '/velodyne_points']"
    )


def test_the_vehicle_replays_a_raw_image_bag_with_tf_and_truth(sim_run, tmp_path):
    import cv2

    from monoloc.client.bag_replay import read_bag_run

    _, run = sim_run
    bag = write_sim_bag(run, tmp_path / "replay_tf", poses="tf", three_d="none")
    replay = read_bag_run(bag)
    assert len(replay) == len(run.images)
    np.testing.assert_allclose(replay.timestamps_s - replay.timestamps_s[0], run.times_s, atol=1e-6)
    for i in (0, len(replay) - 1):  # raw mono8 -> PNG: the same pixels
        png = np.frombuffer(replay.image_bytes(i), dtype=np.uint8)
        sent = cv2.imdecode(png, cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(sent, cv2.imread(str(run.images[i]), cv2.IMREAD_GRAYSCALE))
    # no Odometry: speed and yaw rate differentiated from /tf (straight, steady street)
    assert any("differentiated from /tf" in note for note in replay.notes)
    np.testing.assert_allclose(replay.signals[:, 0], run.signals[:, 0], atol=0.05)
    np.testing.assert_allclose(replay.signals[:, 1], run.signals[:, 1], atol=0.01)
    assert replay.truth_world is None

    bag = write_sim_bag(run, tmp_path / "replay_odom", image="compressed", three_d="none")
    replay = read_bag_run(bag, {"odometry": "/odom", "truth": "/odom"})
    np.testing.assert_allclose(replay.signals, run.signals, atol=1e-12)
    truth = planar_from_T_world_from_cam(run.T_world_from_cam)
    np.testing.assert_allclose(replay.truth_world, truth, atol=1e-9)
    with pytest.raises(InvalidInputError, match="unknown topic role"):
        read_bag_run(bag, {"camera": "/camera/image_raw/compressed"})

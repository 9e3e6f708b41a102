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
    # without CameraInfo the camera is unknown: the drive refuses before its first frame
    bag = write_sim_bag(run, tmp_path / "replay_no_info", camera_info=False, three_d="none")
    assert read_bag_run(bag).intrinsics is None


# The layouts recorders produce (rosbag_helpers' ``poses``), in ROS 2 sqlite3 and mcap
# storage and ROS 1 bags: each gives back the camera's true poses.
LAYOUTS = [
    ("sqlite3", "pose_stamped", "raw"),
    ("mcap", "odometry_camera", "compressed"),
    ("ros1", "odometry", "compressed"),
    ("sqlite3", "tf_chain", "raw"),
    ("ros1", "tf_chain", "raw"),
    ("mcap", "tf", "compressed"),
]


def _bag_path(tmp_path: Path, storage: str, name: str) -> Path:
    return tmp_path / (f"{name}.bag" if storage == "ros1" else name)


@pytest.mark.parametrize(("storage", "poses", "image"), LAYOUTS)
def test_every_recorded_layout_gives_the_camera_poses(sim_run, tmp_path, storage, poses, image):
    root, run = sim_run
    out = _bag_path(tmp_path, storage, f"{poses}_{image}")
    bag = write_sim_bag(run, out, image=image, poses=poses, storage=storage)
    source = read_rosbag_run(bag)
    assert len(source.frames) == len(run.images) and not source.read_skips
    T = np.stack([f.T_world_from_cam for f in source.frames])
    np.testing.assert_allclose(T, run.T_world_from_cam, atol=1e-6)
    assert source.intrinsics == read_kitti_sequence(root, "00").intrinsics


def test_a_ros1_bag_is_ingested_like_the_kitti_run(sim_run, tmp_path, factory, make_map, make_run):
    root, run = sim_run
    bag = write_sim_bag(run, tmp_path / "car.bag", image="compressed", storage="ros1")
    source = read_rosbag_run(bag)
    _, summary = _ingest(factory, make_map, make_run, source, "ros1")
    _, kitti_summary = _ingest(factory, make_map, make_run, read_kitti_sequence(root, "00"), "k")
    assert summary.entries_added == kitti_summary.entries_added >= 4


def test_a_bag_without_camera_info_takes_the_maps_camera(sim_run, tmp_path):
    root, run = sim_run
    bag = write_sim_bag(run, tmp_path / "no_info", camera_info=False)
    with pytest.raises(InvalidInputError, match="no CameraInfo topic"):
        read_rosbag_run(bag)
    camera = read_kitti_sequence(root, "00").intrinsics
    source = read_rosbag_run(bag, fallback_intrinsics=camera)
    assert source.intrinsics == camera and len(source.frames) == len(run.images)


def _cli(monkeypatch, *args) -> int:
    from monoloc.cli import main

    monkeypatch.setattr(sys, "argv", ["monoloc", *args])
    try:
        main()
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


def test_cli_ingests_a_bag_without_camera_info_and_refuses_one_without_poses(
    sim_run, tmp_path, monkeypatch, capsys
):
    root, run = sim_run
    monkeypatch.setenv("MONOLOC_DATA_DIR", str(tmp_path / "data"))
    camera = read_kitti_sequence(root, "00").intrinsics
    spec = ["--fx", str(camera.fx), "--fy", str(camera.fy), "--cx", str(camera.cx)]
    spec += ["--cy", str(camera.cy), "--width", str(camera.width_px)]
    spec += ["--height", str(camera.height_px)]
    assert _cli(monkeypatch, "map", "create", "street", *spec) == 0
    no_info = write_sim_bag(run, tmp_path / "no_info", camera_info=False, poses="pose_stamped")
    code = _cli(monkeypatch, "map", "ingest", "--map", "street", "--format", "rosbag", str(no_info))
    out = capsys.readouterr()
    assert code == 0, out.err
    assert "entries added" in out.out
    no_poses = write_sim_bag(run, tmp_path / "no_poses.bag", poses="none", storage="ros1")
    code = _cli(
        monkeypatch, "map", "ingest", "--map", "street", "--format", "rosbag", str(no_poses)
    )
    err = capsys.readouterr().err.strip()
    assert code == 1 and "\n" not in err and "Traceback" not in err
    assert err.startswith("error:") and "no poses" in err and "--topic pose=" in err


def test_the_vehicle_replays_every_layout_with_the_mounting_of_tf_static(sim_run, tmp_path):
    from rosbag_helpers import T_BASE_FROM_CAM

    from monoloc.client.bag_replay import read_bag_run
    from monoloc.client.drive import run_filter_config
    from monoloc.client.particle_filter import FilterConfig

    _, run = sim_run
    lever_arm_m = T_BASE_FROM_CAM[0, 3]
    for storage, poses, image in LAYOUTS:
        out = _bag_path(tmp_path, storage, f"replay_{poses}_{image}")
        bag = write_sim_bag(run, out, image=image, poses=poses, storage=storage, three_d="none")
        replay = read_bag_run(bag)
        assert len(replay) == len(run.images), (storage, poses)
        assert len(replay.image_bytes(0)) > 0
        # the camera's own intrinsics from its CameraInfo, sent with every frame
        cam = replay.intrinsics
        np.testing.assert_allclose(
            [cam.fx, cam.fy, cam.cx, cam.cy], run.K[[0, 1, 0, 1], [0, 1, 2, 2]]
        )
        # speed and yaw rate: the twist, or differentiated from the poses
        np.testing.assert_allclose(replay.signals[:, 0], run.signals[:, 0], atol=0.05)
        np.testing.assert_allclose(replay.signals[:, 1], run.signals[:, 1], atol=0.01)
        if poses == "odometry_camera":  # the speeds are the camera's own: no lever arm
            assert replay.lever_arm_m is None
        else:  # base_link -> camera of /tf_static, used by the motion model
            assert replay.lever_arm_m == pytest.approx(lever_arm_m, abs=1e-9), (storage, poses)
            # the whole base_link -> camera transform: 1.2 m ahead, 1.5 m up, looking ahead
            mounting = replay.mounting
            np.testing.assert_allclose(
                mounting.T_vehicle_from_cam, T_BASE_FROM_CAM, atol=1e-9, err_msg=poses
            )
            assert mounting.height_m == pytest.approx(1.5, abs=1e-9)
            mount = run_filter_config(FilterConfig(), replay).motion.mount
            assert mount.x_m == pytest.approx(lever_arm_m, abs=1e-9)
            assert mount.y_m == pytest.approx(0.0, abs=1e-9)
    # a truth named, and nothing else to take speeds from: the hint names the drive's role
    bag = write_sim_bag(run, tmp_path / "truth_only", three_d="none")
    with pytest.raises(InvalidInputError, match=r"no poses.*--topic odometry="):
        read_bag_run(bag, {"truth": "/odom"})
    replay = read_bag_run(
        write_sim_bag(run, tmp_path / "ps_truth", poses="pose_stamped", three_d="none"),
        {"truth": "/vehicle/pose", "odometry": "/vehicle/pose"},
    )
    truth = planar_from_T_world_from_cam(run.T_world_from_cam)
    np.testing.assert_allclose(replay.truth_world, truth, atol=1e-6)

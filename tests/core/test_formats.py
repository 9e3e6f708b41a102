"""The dataset text formats: every writer's output read back (through a StringIO, as evo
tests its file interface), and each kind of malformed file refused naming file and line."""

from __future__ import annotations

import io
import re

import numpy as np
import pytest

from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.formats import kitti, tum, vehicle
from monoloc.core.geometry import R_from_quaternion_xyzw


def _random_poses(n: int, seed: int = 0) -> np.ndarray:
    """(n, 4, 4) rigid transforms with random rotations and translations of tens of m."""
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        T[i, :3, :3] = R_from_quaternion_xyzw(rng.normal(size=4))
        T[i, :3, 3] = rng.normal(scale=30.0, size=3)
    return T


def _read_back(write, read, *args, **kwargs):
    buffer = io.StringIO()
    write(buffer, *args, **kwargs)
    buffer.seek(0)
    return read(buffer), buffer.getvalue()


def test_kitti_poses_round_trip():
    T = _random_poses(5)
    back, text = _read_back(kitti.write_poses, kitti.read_poses, T)
    assert len(text.splitlines()) == 5 and all(len(ln.split()) == 12 for ln in text.splitlines())
    np.testing.assert_allclose(back, T, rtol=1e-8, atol=1e-9)


def test_kitti_times_round_trip():
    timestamps_s = np.array([0.0, 0.103, 0.2071, 1234.567])
    back, _ = _read_back(kitti.write_times, kitti.read_times, timestamps_s)
    assert back.shape == (4,)
    np.testing.assert_allclose(back, timestamps_s, rtol=1e-6)


def test_kitti_calib_round_trip():
    K = np.array([[718.856, 0.0, 607.1928], [0.0, 718.856, 185.2157], [0.0, 0.0, 1.0]])
    projections = tuple(np.hstack([K, [[-K[0, 0] * b], [0.0], [0.0]]]) for b in (0.0, 0.54))
    calib = kitti.KittiCalib(projections, _random_poses(1, seed=3)[0])
    back, text = _read_back(kitti.write_calib, kitti.read_calib, calib)
    assert [line.split(":")[0] for line in text.splitlines()] == ["P0", "P1", "Tr"]
    assert len(back.P_image_from_cam0) == 2
    for P, P_back in zip(projections, back.P_image_from_cam0, strict=True):
        np.testing.assert_allclose(P_back, P, rtol=1e-12)
    np.testing.assert_allclose(back.T_cam0_from_lidar, calib.T_cam0_from_lidar, atol=1e-12)


def test_kitti_calib_of_a_camera_reads_back_its_camera_and_baseline():
    K = np.array([[718.856, 0.0, 607.1928], [0.0, 718.856, 185.2157], [0.0, 0.0, 1.0]])
    T = _random_poses(1, seed=3)[0]
    calib = kitti.KittiCalib.from_camera(K, T, stereo_baseline_m=0.54)
    back, _ = _read_back(kitti.write_calib, kitti.read_calib, calib)
    assert len(back.P_image_from_cam0) == 4  # P0..P3, as KITTI lists them
    assert back.pinhole == pytest.approx((718.856, 718.856, 607.1928, 185.2157))
    assert back.intrinsics(1241, 376).width_px == 1241
    assert back.stereo_baseline_m() == pytest.approx(0.54, rel=1e-9)
    np.testing.assert_allclose(back.T_cam0_from_lidar, T, atol=1e-11)
    skewed = kitti.KittiCalib((back.P_image_from_cam0[0], back.P_image_from_cam0[0] * 1.01), T)
    with pytest.raises(InvalidInputError, match="not a rectified stereo pair"):
        skewed.stereo_baseline_m()
    with pytest.raises(InvalidInputError, match="no P1 line"):
        kitti.KittiCalib(back.P_image_from_cam0[:1], T).stereo_baseline_m()


def test_kitti_scans_round_trip_without_their_non_finite_points(tmp_path):
    points = np.random.default_rng(0).normal(size=(50, 4)).astype(np.float32)
    points[7, 1] = np.nan
    kitti.write_scan(tmp_path / "000000.bin", points)
    back = kitti.read_scan(tmp_path / "000000.bin")
    np.testing.assert_array_equal(back, np.delete(points, 7, axis=0))
    (tmp_path / "000001.bin").write_bytes(b"\0" * 20)
    with pytest.raises(InputFileError, match=r"000001\.bin: .* not a multiple of 16"):
        kitti.read_scan(tmp_path / "000001.bin")


def test_tum_camera_json_and_depth_encoding_read_back(tmp_path):
    from monoloc.core.camera import CameraIntrinsics

    camera = CameraIntrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
    tum.write_camera_json(tmp_path / "camera.json", camera, {"world_frame": "z-up"})
    path, data = tum.read_camera_json(tmp_path)
    assert path == tmp_path / "camera.json" and data["world_frame"] == "z-up"
    assert (data["fx"], data["width"], data["depth_scale_per_m"]) == (525.0, 640, 5000.0)
    # camera.yaml beside it, in ROS's layout
    from monoloc.core.formats.camera_yaml import read_camera_yaml

    assert read_camera_yaml(tmp_path / "camera.yaml").intrinsics == camera
    depth_m = np.array([[1.0, 0.0], [np.nan, 20.0]])
    raw = tum.encode_depth(depth_m)
    assert raw.dtype == np.uint16 and raw.tolist() == [[5000, 0], [0, 0]]  # 20 m: too far


def test_tum_trajectory_round_trip():
    T = _random_poses(6, seed=1)
    timestamps_s = 1305031102.175304 + 0.033 * np.arange(6)
    back, text = _read_back(
        tum.write_trajectory, tum.read_trajectory, timestamps_s, T, comments=["ground truth"]
    )
    assert text.startswith("# ground truth\n")
    assert len(back) == 6
    np.testing.assert_allclose(back.timestamps_s, timestamps_s, atol=1e-6)
    np.testing.assert_allclose(back.T_world_from_cam, T, atol=1e-8)
    np.testing.assert_allclose(back.position_world_m, T[:, :3, 3], atol=1e-9)
    assert np.all(back.q_world_from_cam_xyzw[:, 3] >= 0)  # qw >= 0 as written


def test_tum_writer_precision_is_the_callers():
    T = _random_poses(1)
    buffer = io.StringIO()
    tum.write_trajectory(buffer, [2.5], T, position_decimals=6, quaternion_decimals=7)
    fields = buffer.getvalue().split()
    assert fields[0] == "2.500000"
    assert [len(f.split(".")[1]) for f in fields[1:]] == [6, 6, 6, 7, 7, 7, 7]
    with pytest.raises(InvalidInputError, match="differ in length"):
        tum.write_trajectory(io.StringIO(), [0.0, 1.0], T)


def test_tum_file_list_round_trip_and_existence(tmp_path):
    stamps = np.array([10.0, 10.033333, 10.066667])
    names = [f"rgb/{tum.stamp_text(t)}.png" for t in stamps]
    (back_stamps, back_names), text = _read_back(
        tum.write_file_list, tum.read_file_list, stamps, names, comments=["color images"]
    )
    assert text.splitlines()[:2] == ["# color images", "10.000000 rgb/10.000000.png"]
    assert back_names == names
    np.testing.assert_allclose(back_stamps, stamps, atol=1e-6)
    # With a root, every listed file must exist; the error names the listing's line.
    (tmp_path / "rgb").mkdir()
    for name in names[:2]:
        (tmp_path / name).write_bytes(b"png")
    listing = tmp_path / "rgb.txt"
    listing.write_text(text)
    with pytest.raises(InputFileError, match=r"rgb\.txt:4: lists rgb/10\.066667\.png, which"):
        tum.read_file_list(listing, root=tmp_path)
    (tmp_path / names[2]).write_bytes(b"png")
    assert tum.read_file_list(listing, root=tmp_path)[1] == names


def test_vehicle_round_trip():
    timestamps_s = np.array([0.0, 0.1, 0.2])
    speed_mps = np.array([10.748567, 10.689141, 0.0])
    yaw_rate_radps = np.array([-0.0079105, 0.0041296, 0.5])
    back, text = _read_back(
        vehicle.write_vehicle, vehicle.read_vehicle, timestamps_s, speed_mps, yaw_rate_radps
    )
    assert text.splitlines()[0] == "0.000000 10.748567 -0.0079105"
    np.testing.assert_array_equal(back.timestamps_s, timestamps_s)
    np.testing.assert_array_equal(back.speed_mps, speed_mps)
    np.testing.assert_array_equal(back.yaw_rate_radps, yaw_rate_radps)
    with pytest.raises(InvalidInputError, match="differ in length"):
        vehicle.write_vehicle(io.StringIO(), timestamps_s, speed_mps[:2], yaw_rate_radps)


def test_readers_take_a_path_and_skip_comments_and_blank_lines(tmp_path):
    path = tmp_path / "vehicle.txt"
    path.write_text("# t v w\n\n0.0 1.0 0.0\n  # indented comment\n0.1 2.0 0.1\n")
    assert len(vehicle.read_vehicle(path)) == 2
    assert len(vehicle.read_vehicle(str(path))) == 2
    with pytest.raises(InputFileError, match=r"nothing\.txt: cannot read vehicle signal"):
        vehicle.read_vehicle(tmp_path / "nothing.txt")


_POSE = "1 0 0 0 0 1 0 0 0 0 1 0"
_GT = "1.0 0 0 0 0 0 0 1"
_CALIB = ["P0: 700 0 600 0 0 700 180 0 0 0 1 0", "Tr: " + _POSE]
_BAD = [
    # (reader, file name, text, line, message)
    (kitti.read_poses, "00.txt", f"{_POSE}\n{_POSE} 1\n", 2, "pose has 13 values, expected 12"),
    (kitti.read_poses, "00.txt", f"{_POSE}\n1 0 0 x 0 1 0 0 0 0 1 0\n", 2, "not a number: 'x'"),
    (kitti.read_poses, "00.txt", "nan 0 0 0 0 1 0 0 0 0 1 0\n", 1, "pose contains NaN or inf"),
    (kitti.read_poses, "00.txt", "1 0 0 inf 0 1 0 0 0 0 1 0\n", 1, "pose contains NaN or inf"),
    (kitti.read_poses, "00.txt", f"{_POSE}\n2 0 0 0 0 1 0 0 0 0 1 0\n", 2, "pose is not rigid"),
    (kitti.read_poses, "00.txt", "# nothing\n", None, "no poses"),
    (kitti.read_times, "times.txt", "0.0\n0.1 0.2\n", 2, "timestamp has 2 values, expected 1"),
    (kitti.read_times, "times.txt", "0.0\nabc\n", 2, "not a number: 'abc'"),
    (kitti.read_times, "times.txt", "0.0\n-inf\n", 2, "timestamp contains NaN or inf"),
    (kitti.read_calib, "calib.txt", _CALIB[0] + "\n", None, "no Tr line"),
    (kitti.read_calib, "calib.txt", "P0 700 0\n", 1, "expected 'NAME: numbers'"),
    (kitti.read_calib, "calib.txt", "P0: 700 0 600\n" + _CALIB[1], 1, "P0 has 3 numbers"),
    (kitti.read_calib, "calib.txt", _CALIB[0] + "\nTr: 1 0 0 q 0 1 0 0 0 0 1 0", 2, "not a numb"),
    (kitti.read_calib, "calib.txt", _CALIB[0] + "\nTr: 1 0 0 nan 0 1 0 0 0 0 1 0", 2, "Tr contai"),
    (kitti.read_calib, "calib.txt", _CALIB[0] + "\nTr: " + "1 " * 12, 2, "Tr is not a rigid"),
    (kitti.read_calib, "calib.txt", "P0: " + "-5 " * 12 + "\n" + _CALIB[1], 1, "P0 is not a pin"),
    (
        kitti.read_calib,
        "calib.txt",
        "\n".join([*_CALIB, "P2: " + _POSE]),
        None,
        "projections P0, P2 are not",
    ),
    (
        tum.read_trajectory,
        "gt.txt",
        f"{_GT}\n2.0 0 0 0 0 0 1\n",
        2,
        "ground-truth pose has 7 values",
    ),
    (tum.read_trajectory, "gt.txt", f"{_GT}\n2.0 0 0 0 0 0 0 one\n", 2, "not a number: 'one'"),
    (tum.read_trajectory, "gt.txt", "1.0 nan 0 0 0 0 0 1\n", 1, "ground-truth pose contains NaN"),
    (tum.read_trajectory, "gt.txt", f"{_GT}\n2.0 0 0 0 0 0 0 7\n", 2, "quaternion norm 7.0000"),
    (tum.read_trajectory, "gt.txt", f"{_GT}\n2.0 0 0 0 0 0 0 0\n", 2, "quaternion norm 0.0000"),
    (tum.read_trajectory, "gt.txt", "", None, "no ground-truth poses"),
    (tum.read_file_list, "rgb.txt", "1.0 rgb/1.png\n2.0\n", 2, "expected 'timestamp filename'"),
    (tum.read_file_list, "rgb.txt", "1.0 a.png b.png\n", 1, "expected 'timestamp filename'"),
    (tum.read_file_list, "rgb.txt", "t1 rgb/1.png\n", 1, "not a number: 't1'"),
    (tum.read_file_list, "rgb.txt", "nan rgb/1.png\n", 1, "timestamp contains NaN or inf"),
    (tum.read_file_list, "rgb.txt", "# only\n", None, "lists no files"),
    (
        vehicle.read_vehicle,
        "vehicle.txt",
        "0.0 1.0\n",
        1,
        "vehicle signal has 2 values, expected 3",
    ),
    (vehicle.read_vehicle, "vehicle.txt", "0.0 1.0 0.0\n0.4 fast 0.0\n", 2, "not a number"),
    (vehicle.read_vehicle, "vehicle.txt", "0.0 inf 0.0\n", 1, "vehicle signal contains NaN"),
    (vehicle.read_vehicle, "vehicle.txt", "\n", None, "no vehicle signals"),
]


@pytest.mark.parametrize(("read", "name", "text", "line", "message"), _BAD)
def test_malformed_files_are_refused_naming_file_and_line(
    tmp_path, read, name, text, line, message
):
    path = tmp_path / name
    path.write_text(text)
    where = re.escape(f"{name}:{line}: " if line is not None else f"{name}: ")
    with pytest.raises(InvalidInputError, match=where + re.escape(message)) as info:
        read(path)
    assert isinstance(info.value, InputFileError)
    assert info.value.path == path and info.value.line == line


def test_a_handle_without_a_name_is_called_stream():
    with pytest.raises(InputFileError, match=r"^<stream>:1: pose has 1 values"):
        kitti.read_poses(io.StringIO("1\n"))


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_pose_bag_round_trip(tmp_path, storage):
    """write_pose_bag's Odometry messages read back (rosbags' reader, monoloc's Odometry
    reading) as the same stamps, frames and poses; bad input writes nothing."""
    from monoloc.core.formats import rosbag as bag

    T = _random_poses(7, seed=3)
    times_s = 1_700_000_000.0 + np.cumsum(np.full(7, 0.1))
    path = bag.write_pose_bag(
        tmp_path / "track", times_s, T, camera_frame="cam0_optical", storage=storage
    )
    with bag.open_bag(path) as reader:
        assert bag.topic_types(reader) == {bag.ESTIMATE_TOPIC: bag.ODOMETRY}
        track = bag.read_odometry(reader, bag.ESTIMATE_TOPIC)
    assert (track.world, track.body) == ("map", "cam0_optical")
    np.testing.assert_allclose(track.pose_rows[:, 0], times_s, rtol=0, atol=1e-6)
    back = np.stack([bag.T_from_pose_row(row) for row in track.pose_rows])
    np.testing.assert_allclose(back, T, atol=1e-9)
    assert np.all(track.signal_rows[:, 1:] == 0.0)  # no twist is estimated

    with pytest.raises(InputFileError, match="already exists"):
        bag.write_pose_bag(path, times_s, T)
    bad = [
        (times_s[:3], T, "must be \\(3, 4, 4\\)"),
        (times_s[::-1], T, "increasing"),
        (times_s, T * np.nan, "finite"),
        (times_s[:0], T[:0], "no poses"),
    ]
    for times, poses, message in bad:
        with pytest.raises(InvalidInputError, match=message):
            bag.write_pose_bag(tmp_path / "bad", times, poses)
        assert not (tmp_path / "bad").exists()
    with pytest.raises(InvalidInputError, match="sqlite3 or mcap"):
        bag.write_pose_bag(tmp_path / "bad", times_s, T, storage="db3")

"""The KITTI reader: calibration, poses (z-up conversion), frame ranges, and each kind of
bad input failing with the file and line named."""

from __future__ import annotations

import numpy as np
import pytest

from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.geometry import kitti_to_zup
from monoloc.server.ingest.common import parse_frame_range
from monoloc.server.ingest.sources import read_kitti_sequence


def test_reads_calibration_poses_and_frames(kitti_root):
    seq = read_kitti_sequence(kitti_root.root)  # dataset root with one sequence
    assert seq.sequence == "00" and seq.n_frames == 8 == seq.n_frames_total
    assert seq.intrinsics == kitti_root.camera
    np.testing.assert_allclose(seq.T_cam_from_lidar, kitti_root.T_cam_from_lidar, atol=1e-12)
    frame = seq.frames[5]
    assert frame.index == 5 and frame.timestamp_s == pytest.approx(0.5)
    assert frame.image_path.name == "000005.png" and frame.scan_path.name == "000005.bin"
    np.testing.assert_allclose(
        frame.T_world_from_cam, kitti_to_zup(kitti_root.T_kitti_from_cam[5]), atol=1e-9
    )
    # z-up: KITTI's forward (z) is the world's x, its down (y) the world's -z.
    assert frame.T_world_from_cam[0, 3] == pytest.approx(kitti_root.T_kitti_from_cam[5, 2, 3])
    loaded = seq.load(frame)
    assert loaded.image_gray.shape == (kitti_root.camera.height_px, kitti_root.camera.width_px)
    assert loaded.source.points_lidar.shape[1] == 4


def test_sequence_folder_and_frame_range(kitti_root):
    seq = read_kitti_sequence(kitti_root.sequence_dir, frames=parse_frame_range("2:6"))
    assert [f.index for f in seq.frames] == [2, 3, 4, 5] and seq.n_frames_total == 8
    tail = read_kitti_sequence(kitti_root.root, "00", parse_frame_range("-3:"))
    assert [f.index for f in tail.frames] == [5, 6, 7]
    assert parse_frame_range("0:3860") == slice(0, 3860, None)
    assert parse_frame_range("::2") == slice(None, None, 2)
    with pytest.raises(InvalidInputError, match="frame range"):
        parse_frame_range("3-5")


def _lines(path):
    return path.read_text().splitlines()


def test_missing_image_is_named(kitti_copy):
    (kitti_copy.sequence_dir / "image_0" / "000003.png").unlink()
    with pytest.raises(InputFileError, match=r"image_0/000003\.png.*missing"):
        read_kitti_sequence(kitti_copy.root)


def test_missing_scan_folder_is_named(kitti_copy):
    import shutil

    shutil.rmtree(kitti_copy.sequence_dir / "velodyne")
    with pytest.raises(InputFileError, match="velodyne: folder is missing"):
        read_kitti_sequence(kitti_copy.root)


def test_mismatched_counts(kitti_copy):
    times = kitti_copy.sequence_dir / "times.txt"
    times.write_text("\n".join(_lines(times)[:-1]) + "\n")
    with pytest.raises(InputFileError, match=r"times\.txt: has 7 timestamps but .*00\.txt has 8"):
        read_kitti_sequence(kitti_copy.root)


def test_extra_image_is_a_count_mismatch(kitti_copy):
    images = kitti_copy.sequence_dir / "image_0"
    (images / "000008.png").write_bytes((images / "000007.png").read_bytes())
    with pytest.raises(InputFileError, match="holds 9 .png files but .* has 8 frames"):
        read_kitti_sequence(kitti_copy.root)


def test_nan_pose_names_the_line(kitti_copy):
    poses = kitti_copy.root / "poses" / "00.txt"
    lines = _lines(poses)
    lines[3] = " ".join(["nan"] + lines[3].split()[1:])
    poses.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputFileError, match=r"poses/00\.txt:4: pose contains NaN") as info:
        read_kitti_sequence(kitti_copy.root)
    assert info.value.line == 4


def test_pose_with_wrong_number_of_values_and_non_rigid_pose(kitti_copy):
    poses = kitti_copy.root / "poses" / "00.txt"
    lines = _lines(poses)
    poses.write_text("\n".join(lines[:2] + [lines[2] + " 1.0"] + lines[3:]) + "\n")
    with pytest.raises(InputFileError, match=r"00\.txt:3: pose has 13 values, expected 12"):
        read_kitti_sequence(kitti_copy.root)
    values = lines[6].split()
    values[0] = "2.0"  # a scaled rotation
    poses.write_text("\n".join(lines[:6] + [" ".join(values)] + lines[7:]) + "\n")
    with pytest.raises(InputFileError, match=r"00\.txt:7: pose is not rigid"):
        read_kitti_sequence(kitti_copy.root)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda ls: [" ".join(ls[0].split()[:10])] + ls[1:], r"calib\.txt:1: P0 has 9 numbers"),
        (lambda ls: ls[:4], r"calib\.txt: no Tr line"),
        (lambda ls: [ls[0].replace("P0:", "P0 ")] + ls[1:], r"calib\.txt:1: expected 'NAME: "),
        (lambda ls: ls[:4] + ["Tr: " + " ".join(["1"] * 12)], r"calib\.txt:5: Tr is not a rigid"),
        (lambda ls: ["P0: " + " ".join(["-5"] * 12)] + ls[1:], r"calib\.txt:1: P0 is not a pin"),
    ],
)
def test_bad_calibration_names_the_line(kitti_copy, edit, message):
    calib = kitti_copy.sequence_dir / "calib.txt"
    calib.write_text("\n".join(edit(_lines(calib))) + "\n")
    with pytest.raises(InputFileError, match=message):
        read_kitti_sequence(kitti_copy.root)


def test_truncated_scan_is_named(kitti_copy):
    scan = kitti_copy.sequence_dir / "velodyne" / "000002.bin"
    scan.write_bytes(scan.read_bytes()[:-3])
    with pytest.raises(InputFileError, match=r"000002\.bin: size .* not a multiple of 16"):
        read_kitti_sequence(kitti_copy.root)


def test_several_sequences_need_a_choice(kitti_copy):
    import shutil

    shutil.copytree(kitti_copy.sequence_dir, kitti_copy.root / "sequences" / "01")
    with pytest.raises(InvalidInputError, match=r"choose one with --sequence"):
        read_kitti_sequence(kitti_copy.root)
    with pytest.raises(InputFileError, match=r"01\.txt: poses file is missing"):
        read_kitti_sequence(kitti_copy.root, "01")
    assert read_kitti_sequence(kitti_copy.root, "00").n_frames == 8

"""Reading recorded runs as a vehicle replays them: a tiny sim KITTI run (signals from
vehicle.txt, truth from poses/NN.txt, the rig's lever arm from dataset.json), the same
sequence without vehicle.txt (signals derived from the poses, and said so), frame
ranges, and malformed files named in the error."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from monoloc.client.replay import (
    SignalNoise,
    parse_frames,
    read_kitti_run,
    read_run,
    read_tum_run,
    rig_lever_arm_m,
    signals_from_truth,
)
from monoloc.core.errors import InvalidInputError, NotFoundError
from monoloc.core.geometry import kitti_to_zup, planar_from_T_world_from_cam

N_FRAMES = 12
LEVER_ARM_M = 1.3  # not the sim's default (1.0), so reading it back means something


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory) -> Path:
    """Dataset root of one sim map run: 12 frames, quarter-size images, no LiDAR, exact
    signals (the readers do not look at pixels)."""
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.recording import RecordingErrors
    from monoloc.sim.vehicle import SensorRig

    root = tmp_path_factory.mktemp("replay_sim")
    config = GenerateConfig(
        runs=("map",),
        max_frames=N_FRAMES,
        image_scale=0.25,
        write_lidar=False,
        errors=RecordingErrors.none(),
        rig=SensorRig(camera_ahead_of_rear_axle_m=LEVER_ARM_M),
        seed=1,
    )
    generate_dataset(config, root)
    return root


def _copy_dataset(root: Path, dest: Path) -> Path:
    shutil.copytree(root / "sequences", dest / "sequences")
    shutil.copytree(root / "poses", dest / "poses")
    return dest


def test_kitti_run_reads_frames_signals_and_truth(sim_run):
    run = read_kitti_run(sim_run, "00")
    vehicle = np.loadtxt(sim_run / "sequences" / "00" / "vehicle.txt")
    poses = np.loadtxt(sim_run / "poses" / "00.txt").reshape(-1, 3, 4)
    T = np.tile(np.eye(4), (len(poses), 1, 1))
    T[:, :3] = poses
    assert len(run) == N_FRAMES and run.name == "kitti:00"
    assert [p.name for p in run.image_paths] == [f"{i:06d}.png" for i in range(N_FRAMES)]
    np.testing.assert_allclose(run.timestamps_s, vehicle[:, 0], atol=1e-9)
    np.testing.assert_allclose(run.signals, vehicle[:, 1:3])
    np.testing.assert_allclose(run.truth_world, planar_from_T_world_from_cam(kitti_to_zup(T)))
    assert run.notes == [] and run.lever_arm_m is None  # read_kitti_run alone: no rig
    assert np.all(run.signals[:, 0] > 1.0)  # the sim car is moving


def test_read_run_takes_the_lever_arm_from_dataset_json(sim_run):
    for run in (read_run(sim_run, "00"), read_run(sim_run / "sequences" / "00")):
        assert run.lever_arm_m == pytest.approx(LEVER_ARM_M)
        assert any("dataset.json" in note and "1.30 m" in note for note in run.notes)
    assert rig_lever_arm_m(sim_run / "sequences") == pytest.approx(LEVER_ARM_M)


def test_without_vehicle_txt_signals_come_from_the_poses_and_it_says_so(sim_run, tmp_path):
    root = _copy_dataset(sim_run, tmp_path / "kitti")
    (root / "sequences" / "00" / "vehicle.txt").unlink()
    exact = read_kitti_run(root, "00", noise=SignalNoise(0.0, 0.0))
    recorded = read_kitti_run(sim_run, "00")
    assert len(exact.notes) == 1 and "no vehicle.txt" in exact.notes[0]
    assert "00.txt" in exact.notes[0]
    # The poses' finite differences match what the car measured (exact sim signals).
    np.testing.assert_allclose(exact.signals[:, 0], recorded.signals[:, 0], atol=0.1)
    np.testing.assert_allclose(exact.signals[:, 1], recorded.signals[:, 1], atol=0.01)
    noisy = read_kitti_run(root, "00", noise=SignalNoise(0.2, 0.02, seed=5))
    again = read_kitti_run(root, "00", noise=SignalNoise(0.2, 0.02, seed=5))
    other = read_kitti_run(root, "00", noise=SignalNoise(0.2, 0.02, seed=6))
    np.testing.assert_array_equal(noisy.signals, again.signals)
    assert not np.allclose(noisy.signals, other.signals)
    assert "0.2 m/s" in noisy.notes[0]
    (root / "poses" / "00.txt").unlink()
    with pytest.raises(InvalidInputError, match="neither vehicle.txt nor ground-truth"):
        read_kitti_run(root, "00")


def test_signals_from_truth_on_a_known_circle():
    # 10 m radius, 5 m/s, counter-clockwise: yaw rate 0.5 rad/s.
    t = np.arange(0.0, 3.0, 0.1)
    angle = 0.5 * t
    truth = np.stack([10 * np.sin(angle), 10 - 10 * np.cos(angle), angle], axis=1)
    signals = signals_from_truth(t, truth, SignalNoise(0.0, 0.0))
    chord = 2 * 10 * np.sin(0.5 * 0.5 * 0.1) / 0.1  # average speed along the chord
    np.testing.assert_allclose(signals[:, 0], chord, rtol=1e-9)
    np.testing.assert_allclose(signals[:, 1], 0.5, rtol=1e-9)


def test_a_frame_range_selects_the_test_part(sim_run):
    run = read_run(sim_run, "00")
    part = run.select(parse_frames("3:9"))
    assert len(part) == 6
    assert part.image_paths == run.image_paths[3:9]
    np.testing.assert_array_equal(part.timestamps_s, run.timestamps_s[3:9])
    np.testing.assert_array_equal(part.signals, run.signals[3:9])
    np.testing.assert_array_equal(part.truth_world, run.truth_world[3:9])
    assert part.lever_arm_m == run.lever_arm_m
    assert "frames 3..8 of 12 selected (6 frames)" in part.notes
    assert len(run.select(parse_frames("-4:"))) == 4
    assert run.select(parse_frames(None)).notes == run.notes
    for bad in ("5", "a:b", "1:2:3"):
        with pytest.raises(InvalidInputError, match="A:B"):
            parse_frames(bad)


def test_malformed_vehicle_txt_is_refused_naming_file_and_line(sim_run, tmp_path):
    root = _copy_dataset(sim_run, tmp_path / "kitti")
    vehicle = root / "sequences" / "00" / "vehicle.txt"
    lines = vehicle.read_text().splitlines()
    vehicle.write_text("\n".join(lines[:-1]) + "\n")
    with pytest.raises(InvalidInputError, match=f"vehicle.txt: {N_FRAMES - 1} lines"):
        read_kitti_run(root, "00")
    shifted = [f"{float(line.split()[0]) + 0.05:.6f} 5.0 0.0" for line in lines]
    vehicle.write_text("\n".join(shifted) + "\n")
    with pytest.raises(InvalidInputError, match="vehicle.txt: data row 1 has time 0.050000 s"):
        read_kitti_run(root, "00")
    lines[4] = "0.4 fast 0.0"
    vehicle.write_text("\n".join(lines) + "\n")
    with pytest.raises(InvalidInputError, match="vehicle.txt:5: not a number"):
        read_kitti_run(root, "00")
    with pytest.raises(InvalidInputError, match="no such sequence"):
        read_kitti_run(root, "07")
    shutil.rmtree(root / "sequences" / "00" / "image_0")
    with pytest.raises(NotFoundError, match="image_0"):
        read_kitti_run(root, "00")


def _write_tum(root: Path, n: int = 5, missing_image: bool = False) -> Path:
    root.mkdir(parents=True)
    (root / "rgb").mkdir()
    rgb, gt, vehicle = ["# rgb"], ["# gt"], []
    for i in range(n):
        t = 100.0 + 0.1 * i
        name = f"rgb/{i}.png"
        if not (missing_image and i == 2):
            (root / name).write_bytes(b"\x89PNG\r\n\x1a\n")
        rgb.append(f"{t:.4f} {name}")
        # camera looking along +x: R_world_from_cam columns = (-y, -z, +x) world axes
        gt.append(f"{t + 0.004:.4f} {0.5 * i} 0 0.3 -0.5 0.5 -0.5 0.5")
        vehicle.append(f"{t:.4f} 5.0 0.0")
    (root / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    (root / "vehicle.txt").write_text("\n".join(vehicle) + "\n")
    return root


def test_tum_run_matches_truth_by_nearest_time(tmp_path):
    run = read_run(_write_tum(tmp_path / "tum"))
    assert run.name == "tum:tum" and len(run) == 5
    np.testing.assert_allclose(run.truth_world[:, 0], 0.5 * np.arange(5))
    np.testing.assert_allclose(run.truth_world[:, 2], 0.0, atol=1e-9)
    np.testing.assert_allclose(run.signals, [[5.0, 0.0]] * 5)
    with pytest.raises(InvalidInputError, match=r"rgb.txt:4: lists rgb/2.png, which does not"):
        read_tum_run(_write_tum(tmp_path / "tum2", missing_image=True))
    with pytest.raises(InvalidInputError, match="no ground truth within 0.001 s"):
        read_tum_run(tmp_path / "tum", max_dt_s=0.001)


def test_a_run_knows_its_camera_from_its_own_files(sim_run, tmp_path):
    """KITTI: calib.txt's P0 with the images' size; TUM: camera.json; neither: unknown
    (the drive then stops before its first frame, never assuming the map's camera)."""
    import json

    from monoloc.core.formats.kitti import read_calib_file
    from monoloc.core.formats.png import png_size

    seq = sim_run / "sequences" / "00"
    run = read_run(sim_run, "00")
    width, height = png_size(run.image_paths[0])
    fx, fy, cx, cy = read_calib_file(seq / "calib.txt").pinhole
    cam = run.intrinsics
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (fx, fy, cx, cy)
    assert (cam.width_px, cam.height_px) == (width, height) and width < 1241  # quarter size
    assert run.select(slice(2, 5)).intrinsics == cam  # kept by a frame range
    copy = _copy_dataset(sim_run, tmp_path / "kitti")
    (copy / "sequences" / "00" / "calib.txt").unlink()
    assert read_kitti_run(copy, "00").intrinsics is None
    tum = _write_tum(tmp_path / "tum")
    assert read_tum_run(tum).intrinsics is None
    fields = {"fx": 500, "fy": 501, "cx": 319.5, "cy": 239.5, "width": 640, "height": 480}
    (tum / "camera.json").write_text(json.dumps(fields))
    cam = read_tum_run(tum).intrinsics
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (500.0, 501.0, 319.5, 239.5)
    assert (cam.width_px, cam.height_px) == (640, 480)


def test_a_camera_yaml_beside_the_frames_gives_the_lens_and_the_mounting(sim_run, tmp_path):
    """A KITTI-layout run (K also as calib.txt's P0) and a TUM run with a camera.yaml in
    ROS's layout: the replay sends its lens, the motion model takes its mounting (over
    dataset.json's rig); a camera.yaml whose K is not P0, or whose lens model monoloc
    does not know, is refused naming it."""
    import dataclasses

    import yaml

    from monoloc.core.camera import LensDistortion
    from monoloc.core.errors import InputFileError
    from monoloc.core.formats.camera_yaml import write_camera_yaml
    from monoloc.core.mounting import CameraMounting

    copy = _copy_dataset(sim_run, tmp_path / "kitti")
    shutil.copy(sim_run / "dataset.json", copy / "dataset.json")
    seq = copy / "sequences" / "00"
    pinhole = read_run(copy, "00").intrinsics
    assert read_run(copy, "00").mounting.lever_arm_m == pytest.approx(LEVER_ARM_M)  # the rig
    lens = LensDistortion("plumb_bob", (-0.28, 0.09, 0.0006, -0.0004))
    camera = dataclasses.replace(pinhole, distortion=lens)
    mounting = CameraMounting(1.1, 0.2, 1.42, 0.0, 0.052, 0.014)
    write_camera_yaml(seq / "camera.yaml", camera, mounting, "fleet_front")
    run = read_run(copy, "00")
    assert run.intrinsics == camera
    np.testing.assert_allclose(run.mounting.T_vehicle_from_cam, mounting.T_vehicle_from_cam)
    assert (
        run.lever_arm_m == pytest.approx(1.1) and run.select(slice(1, 3)).mounting == run.mounting
    )
    assert any("0.20 m left" in note and "the camera file" in note for note in run.notes)

    data = yaml.safe_load((seq / "camera.yaml").read_text())
    data["camera_matrix"]["data"][0] += 5.0
    (seq / "camera.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(InputFileError, match="is not calib.txt's P0"):
        read_run(copy, "00")
    data["camera_matrix"]["data"][0] -= 5.0
    data["distortion_model"] = "kannala_brandt"
    (seq / "camera.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(InputFileError, match="unknown lens distortion model 'kannala_brandt'"):
        read_run(copy, "00")

    tum = _write_tum(tmp_path / "tum")
    tum_camera = dataclasses.replace(camera, width_px=640, height_px=480)
    write_camera_yaml(tum / "camera.yaml", tum_camera)
    tum_run = read_run(tum)
    assert tum_run.intrinsics == tum_camera and tum_run.mounting is None

"""`monoloc drive --mount-from RUN`: the camera's mounting fitted on a recorded run (KITTI
layout, written with monoloc's format writers: poses, times, vehicle.txt) before any
server is contacted, its height taken from the rig's camera.yaml; a run without poses
is one error line and exit 1."""

from __future__ import annotations

import math
import re
import sys

import cv2
import numpy as np
import pytest

from monoloc import cli
from monoloc.core.camera import CameraIntrinsics
from monoloc.core.formats import kitti, vehicle
from monoloc.core.formats.camera_yaml import write_camera_yaml
from monoloc.core.geometry import zup_to_kitti
from monoloc.core.mounting import CameraMounting

MOUNT = CameraMounting(1.3, -0.25, 1.45, 0.0, math.radians(2.0), math.radians(4.0))
DT_S, SPEED_MPS = 0.1, 6.0


def _recorded_run(root, n: int = 150, poses: bool = True):
    """A KITTI-layout sequence of a car weaving at 6 m/s, its camera at MOUNT."""
    seq = root / "sequences" / "00"
    (seq / "image_0").mkdir(parents=True)
    t = np.arange(n) * DT_S
    yaw_rate = 0.4 * np.sin(2 * np.pi * t / 6.0)
    vehicle_world = np.zeros((n, 3))
    for i in range(1, n):
        x, y, psi = vehicle_world[i - 1]
        turn = yaw_rate[i - 1] * DT_S
        chord = SPEED_MPS * DT_S * np.sinc(turn / (2 * np.pi))
        mid = psi + turn / 2
        vehicle_world[i] = x + chord * math.cos(mid), y + chord * math.sin(mid), psi + turn
    T_world_from_cam = []
    for x, y, psi in vehicle_world:
        T = np.eye(4)
        T[:2, :2] = [[math.cos(psi), -math.sin(psi)], [math.sin(psi), math.cos(psi)]]
        T[:2, 3] = x, y
        T_world_from_cam.append(T @ MOUNT.T_vehicle_from_cam)
    for i in range(n):
        cv2.imwrite(str(seq / "image_0" / f"{i:06d}.png"), np.zeros((24, 32), np.uint8))
    with open(seq / "times.txt", "w") as fh:
        kitti.write_times(fh, t)
    with open(seq / "vehicle.txt", "w") as fh:
        # the signals' yaw rate is the mean over each step, as the trapezoid in the filter
        vehicle.write_vehicle(fh, t, np.full(n, SPEED_MPS), yaw_rate)
    K = np.array([[30.0, 0.0, 15.5], [0.0, 30.0, 11.5], [0.0, 0.0, 1.0]])
    with open(seq / "calib.txt", "w") as fh:
        kitti.write_calib(fh, kitti.KittiCalib.from_camera(K, np.eye(4)))
    camera = CameraIntrinsics(30.0, 30.0, 15.5, 11.5, 32, 24)
    # the rig's camera file: its height and pitch (what a fit on planar poses cannot see)
    write_camera_yaml(
        seq / "camera.yaml", camera, CameraMounting(height_m=1.45, pitch_rad=MOUNT.pitch_rad)
    )
    if poses:
        (root / "poses").mkdir()
        with open(root / "poses" / "00.txt", "w") as fh:
            kitti.write_poses(fh, zup_to_kitti(np.stack(T_world_from_cam)))
    return seq


def _drive(monkeypatch, capsys, *args) -> tuple[int, list[str]]:
    argv = ["drive", *args, "--map", "m", "--key", "k", "--server", "http://127.0.0.1:9"]
    monkeypatch.setattr(sys, "argv", ["monoloc", *argv])
    monkeypatch.setenv("COLUMNS", "400")  # rich: one line per note
    with pytest.raises(SystemExit) as exited:
        cli.main()
    return exited.value.code, capsys.readouterr().err.strip().splitlines()


def test_mount_from_fits_the_mounting_before_the_drive(tmp_path, monkeypatch, capsys):
    seq = _recorded_run(tmp_path / "rec")
    code, err = _drive(monkeypatch, capsys, str(seq), "--mount-from", str(seq))
    fitted = [line for line in err if "fitted on kitti:00" in line]
    assert len(fitted) == 1, err
    numbers = [float(v) for v in re.findall(r"-?\d+\.\d+", fitted[0])]
    ahead, left, height, yaw_deg, pitch_deg = numbers[:5]
    assert ahead == pytest.approx(MOUNT.lever_arm_m, abs=0.02)
    assert left == pytest.approx(MOUNT.lateral_m, abs=0.02)
    assert yaw_deg == pytest.approx(math.degrees(MOUNT.yaw_rad), abs=0.1)
    assert height == pytest.approx(1.45) and pitch_deg == pytest.approx(2.0)  # the rig's
    # then the drive itself: no server on port 9, one line and exit 1
    assert code == 1 and err[-1].startswith("error:"), err


def test_mount_from_a_run_without_poses_is_one_line(tmp_path, monkeypatch, capsys):
    seq = _recorded_run(tmp_path / "rec", n=10, poses=False)
    code, err = _drive(monkeypatch, capsys, str(seq), "--mount-from", str(seq))
    errors = [line for line in err if line.startswith("error:")]
    assert code == 1 and errors == [err[-1]], err
    assert "has no poses to fit a camera mounting on" in err[-1]

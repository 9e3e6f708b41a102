"""The sim's right camera: image_1 beside image_0, P1 in calib.txt with the rig's baseline,
and turning it on changes none of the other files' bytes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from monoloc.core.errors import InvalidInputError
from monoloc.core.formats import kitti
from monoloc.sim.generate import GenerateConfig, generate_dataset
from monoloc.sim.lidar import LidarConfig
from monoloc.sim.recording import RecordingErrors
from monoloc.sim.vehicle import SensorRig


def test_stereo_dataset_has_the_right_camera(stereo_dataset):
    seq = stereo_dataset / "sequences" / "00"
    left = sorted(p.name for p in (seq / "image_0").iterdir())
    assert left == sorted(p.name for p in (seq / "image_1").iterdir()) and len(left) == 6
    P0, P1 = kitti.read_calib(seq / "calib.txt").P_image_from_cam0[:2]
    assert np.allclose(P1[:, :3], P0[:, :3])
    assert (P0[0, 3] - P1[0, 3]) / P0[0, 0] == pytest.approx(SensorRig().stereo_baseline_m)
    info = json.loads((stereo_dataset / "dataset.json").read_text())
    assert "image_1" in info["stereo"]
    # Camera 1 sits to the right: a point's image moves left, by fx * b / z.
    rig = SensorRig()
    offset = np.linalg.inv(rig.T_vehicle_from_cam()) @ rig.T_vehicle_from_cam1()
    assert np.allclose(offset[:3, 3], [rig.stereo_baseline_m, 0.0, 0.0])
    assert np.allclose(offset[:3, :3], np.eye(3))


def test_stereo_leaves_the_other_files_unchanged(stereo_dataset, tmp_path):
    config = GenerateConfig(
        seed=3,
        runs=("map",),
        max_frames=2,
        image_scale=0.5,
        errors=RecordingErrors.none(),
        lidar=LidarConfig(azimuth_steps=1000),
    )
    generate_dataset(config, tmp_path)
    mono, stereo = tmp_path / "sequences" / "00", stereo_dataset / "sequences" / "00"
    assert not (mono / "image_1").exists()
    for name in ("image_0/000000.png", "image_0/000001.png", "velodyne/000001.bin"):
        assert (mono / name).read_bytes() == (stereo / name).read_bytes(), name
    assert (mono / "calib.txt").read_bytes() == (stereo / "calib.txt").read_bytes()


def test_stereo_is_refused_where_it_cannot_be_written():
    with pytest.raises(InvalidInputError, match="urban"):
        GenerateConfig(scenario="indoor", write_stereo=True).validate()
    with pytest.raises(InvalidInputError, match="baseline"):
        GenerateConfig(write_stereo=True, rig=SensorRig(stereo_baseline_m=0.0)).validate()

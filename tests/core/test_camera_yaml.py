"""camera.yaml in ROS's calibration layout (monoloc.core.formats.camera_yaml): files
written by PyYAML in the layout ROS's camera_calibration writes, and CameraInfo's own
field names, are read with their lens and mounting; monoloc's writer is read back by
PyYAML and by monoloc; an unknown distortion model is refused naming it."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from monoloc.core.camera import CameraIntrinsics, LensDistortion
from monoloc.core.errors import InputFileError
from monoloc.core.formats.camera_yaml import (
    parse_simple_yaml,
    read_camera_yaml,
    write_camera_yaml,
)
from monoloc.core.mounting import CameraMounting

LENS = LensDistortion("plumb_bob", (-0.28, 0.09, 0.0006, -0.0004, 0.0))
FLEET = CameraIntrinsics(640.0, 641.0, 511.5, 287.5, 1024, 576, LENS)
MOUNT = CameraMounting(1.2, 0.1, 1.42, 0.0, 0.052, 0.014)


def _ros_layout(camera: CameraIntrinsics) -> dict:
    lens = camera.distortion
    return {
        "image_width": camera.width_px,
        "image_height": camera.height_px,
        "camera_name": "fleet_front",
        "camera_matrix": {"rows": 3, "cols": 3, "data": camera.K.ravel().tolist()},
        "distortion_model": lens.model,
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": list(lens.coefficients)},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": np.eye(3).ravel().tolist()},
        "projection_matrix": {"rows": 3, "cols": 4, "data": [0.0] * 12},
    }


@pytest.mark.parametrize("flow", [False, None, True])
def test_a_pyyaml_file_in_ros_layout_is_read_with_its_lens(tmp_path, flow):
    path = tmp_path / "camera.yaml"
    path.write_text(yaml.safe_dump(_ros_layout(FLEET), default_flow_style=flow))
    got = read_camera_yaml(path)
    assert got.intrinsics == FLEET and got.name == "fleet_front" and got.mounting is None
    assert parse_simple_yaml(path.read_text()) == yaml.safe_load(path.read_text())


def test_camera_info_field_names_and_a_mounting(tmp_path):
    info = {
        "width": 1024,
        "height": 576,
        "K": FLEET.K.ravel().tolist(),
        "D": [0.05, -0.01, 0.002, 0.0],
        "distortion_model": "equidistant",
        "mounting": MOUNT.to_dict(),
    }
    path = tmp_path / "camera.yaml"
    path.write_text("# a fleet camera\n" + yaml.safe_dump(info, default_flow_style=None))
    got = read_camera_yaml(path)
    assert got.intrinsics.distortion == LensDistortion("equidistant", (0.05, -0.01, 0.002, 0.0))
    assert got.mounting == MOUNT


def test_monolocs_writer_is_ros_layout_read_back_by_both(tmp_path):
    path = write_camera_yaml(tmp_path / "camera.yaml", FLEET, MOUNT, "fleet_front")
    data = yaml.safe_load(path.read_text())
    assert data["image_width"] == 1024 and data["distortion_model"] == "plumb_bob"
    assert data["camera_matrix"]["data"] == FLEET.K.ravel().tolist()
    assert data["distortion_coefficients"]["data"] == list(LENS.coefficients)
    assert parse_simple_yaml(path.read_text()) == data
    got = read_camera_yaml(path)
    assert got.intrinsics == FLEET
    np.testing.assert_allclose(got.mounting.T_vehicle_from_cam, MOUNT.T_vehicle_from_cam)
    pinhole = read_camera_yaml(write_camera_yaml(tmp_path / "p.yaml", FLEET.pinhole))
    assert pinhole.intrinsics == FLEET.pinhole  # plumb_bob with zero D, as ROS writes it


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"distortion_model": "kannala_brandt"}, "unknown lens distortion model 'kannala_brandt'"),
        ({"camera_matrix": {"rows": 3, "cols": 3, "data": [1.0, 2.0]}}, "must hold 9"),
        ({"image_width": None}, "needs image_width"),
    ],
)
def test_bad_camera_files_are_refused_naming_the_file_and_the_problem(tmp_path, change, message):
    path = tmp_path / "camera.yaml"
    path.write_text(yaml.safe_dump({**_ros_layout(FLEET), **change}))
    with pytest.raises(InputFileError, match=message) as refused:
        read_camera_yaml(path)
    assert str(path) in str(refused.value)
    path.write_text("image_width: 1024\n  image_height: 576\n")
    with pytest.raises(InputFileError, match="cannot read the camera file"):
        read_camera_yaml(path)

"""Cameras of COLMAP models and kapture datasets: pinhole only, pixel centres moved from
(0.5, 0.5) to OpenCV's (0, 0), anything with distortion refused with its coefficients."""

import pytest

from monoloc.core.errors import InvalidInputError
from monoloc.server.formats.model import pinhole_intrinsics


def test_pinhole_models_read_with_the_half_pixel_shift():
    c = pinhole_intrinsics("PINHOLE", [718.0, 719.0, 607.5, 185.5], 1241, 376, "cam")
    assert (c.fx, c.fy, c.cx, c.cy, c.width_px, c.height_px) == (718, 719, 607, 185, 1241, 376)
    simple = pinhole_intrinsics("SIMPLE_PINHOLE", [500.0, 320.5, 240.5], 640, 480, "cam")
    assert (simple.fx, simple.fy, simple.cx, simple.cy) == (500, 500, 320, 240)
    # a distortion model with zero coefficients is a pinhole camera
    zero = pinhole_intrinsics("OPENCV", [500, 501, 320.5, 240.5, 0, 0, 0, 0], 640, 480, "cam")
    assert (zero.fx, zero.fy) == (500, 501)


@pytest.mark.parametrize(
    "model, params, message",
    [
        ("OPENCV", [500, 500, 320, 240, -0.1, 0.01, 0, 0], r"distortion \[-0.1, 0.01, 0.0, 0.0\]"),
        ("SIMPLE_RADIAL", [500, 320, 240, 0.02], r"distortion \[0.02\]"),
        ("FISHEYE", [1, 2, 3, 4], "monoloc imports pinhole cameras"),
    ],
)
def test_other_cameras_are_refused_with_what_to_do(model, params, message):
    with pytest.raises(InvalidInputError, match=message) as info:
        pinhole_intrinsics(model, params, 640, 480, "sparse/0 camera 1")
    assert str(info.value).startswith("sparse/0 camera 1") and "undistort" in str(info.value)

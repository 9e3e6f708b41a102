"""Cameras of COLMAP models and kapture datasets: pixel centres moved from (0.5, 0.5) to
OpenCV's (0, 0); every COLMAP lens model monoloc reads projects as pycolmap's own camera
does and is written back as the same lens; unknown models and wrong parameter counts are
refused by name."""

import numpy as np
import pytest

from monoloc.core.errors import InvalidInputError
from monoloc.server.formats.model import camera_intrinsics, camera_model_of

LENSES = [
    ("SIMPLE_RADIAL", [500.0, 320.5, 240.5, -0.12]),
    ("RADIAL", [500.0, 320.5, 240.5, -0.2, 0.05]),
    ("OPENCV", [500.0, 505.0, 320.5, 240.5, -0.28, 0.09, 0.0006, -0.0004]),
    ("FULL_OPENCV", [500, 505, 320.5, 240.5, -0.2, 0.04, 0.001, -0.002, 0.01, 0.02, 0.003, 0.001]),
    ("OPENCV_FISHEYE", [300.0, 301.0, 320.5, 240.5, 0.05, -0.01, 0.002, -0.0005]),
    ("OPENCV_FISHEYE", [300.0, 300.0, 320.5, 240.5, 0.0, 0.0, 0.0, 0.0]),  # still a fisheye
    ("SIMPLE_RADIAL_FISHEYE", [300.0, 320.5, 240.5, 0.04]),
    ("RADIAL_FISHEYE", [300.0, 320.5, 240.5, 0.04, -0.005]),
]


def test_pinhole_models_read_with_the_half_pixel_shift():
    c = camera_intrinsics("PINHOLE", [718.0, 719.0, 607.5, 185.5], 1241, 376, "cam")
    assert (c.fx, c.fy, c.cx, c.cy, c.width_px, c.height_px) == (718, 719, 607, 185, 1241, 376)
    assert c.distortion is None
    simple = camera_intrinsics("SIMPLE_PINHOLE", [500.0, 320.5, 240.5], 640, 480, "cam")
    assert (simple.fx, simple.fy, simple.cx, simple.cy) == (500, 500, 320, 240)
    # a distortion model with zero coefficients is a pinhole camera
    zero = camera_intrinsics("OPENCV", [500, 501, 320.5, 240.5, 0, 0, 0, 0], 640, 480, "cam")
    assert (zero.fx, zero.fy) == (500, 501) and zero.distortion is None
    assert camera_model_of(zero) == ("PINHOLE", [500.0, 501.0, 320.5, 240.5])


@pytest.mark.parametrize(
    "model, params", LENSES, ids=[f"{m}-{i}" for i, (m, _) in enumerate(LENSES)]
)
def test_lens_models_project_as_pycolmap_does_and_write_back(model, params):
    import pycolmap

    from monoloc.server.vision.undistort import distort_pixels, undistort_pixels

    camera = pycolmap.Camera(model=model, width=640, height=480, params=params)
    c = camera_intrinsics(model, params, 640, 480, "cam")
    assert c.distortion is not None
    rng = np.random.default_rng(7)
    rays = np.c_[rng.uniform(-0.5, 0.5, (200, 2)), np.ones(200)] * rng.uniform(1, 30, (200, 1))
    colmap_px = camera.img_from_cam(rays)
    ideal_px = rays[:, :2] / rays[:, 2:] * [c.fx, c.fy] + [c.cx, c.cy]
    monoloc_px = distort_pixels(ideal_px, c) + 0.5  # COLMAP's pixel centres
    np.testing.assert_allclose(monoloc_px, colmap_px, atol=1e-6)
    # and the import's undistortion takes COLMAP's pixels back onto the pinhole rays
    np.testing.assert_allclose(undistort_pixels(colmap_px - 0.5, c), ideal_px, atol=1e-3)
    # written back as a model that projects the same
    written, written_params = camera_model_of(c)
    again = pycolmap.Camera(model=written, width=640, height=480, params=written_params)
    np.testing.assert_allclose(again.img_from_cam(rays), colmap_px, atol=1e-9)
    assert camera_intrinsics(written, written_params, 640, 480, "cam") == c


@pytest.mark.parametrize(
    "model, params, message",
    [
        ("FOV", [500, 500, 320, 240, 0.9], "camera model FOV is not one monoloc knows"),
        (
            "THIN_PRISM_FISHEYE",
            [500, 500, 320, 240] + [0.01] * 8,
            "camera model THIN_PRISM_FISHEYE is not one monoloc knows",
        ),
        ("UNKNOWN_CAMERA", [], "camera model UNKNOWN_CAMERA is not one"),
        ("OPENCV", [500, 500, 320, 240, -0.1], r"OPENCV camera takes 8 finite parameters"),
        ("PINHOLE", [500, 500, 320, float("nan")], "PINHOLE camera takes 4 finite"),
    ],
)
def test_other_cameras_are_refused_by_name(model, params, message):
    with pytest.raises(InvalidInputError, match=message) as info:
        camera_intrinsics(model, params, 640, 480, "sparse/0 camera 1")
    assert str(info.value).startswith("sparse/0 camera 1")


def test_a_colmap_model_with_an_unknown_camera_is_refused_in_one_line_leaving_no_map(
    tmp_path, monkeypatch, capsys
):
    """A model written by pycolmap with a FOV camera: `map import` exits 1 naming it."""
    import pycolmap
    from cli_runner import run_monoloc

    reconstruction = pycolmap.Reconstruction()
    camera = pycolmap.Camera(
        model="FOV", width=64, height=48, params=[50, 50, 32, 24, 0.9], camera_id=1
    )
    reconstruction.add_camera_with_trivial_rig(camera)
    image = pycolmap.Image(name="a.png", camera_id=1, image_id=1)
    reconstruction.add_image_with_trivial_frame(image, pycolmap.Rigid3d())
    (tmp_path / "sparse").mkdir()
    (tmp_path / "images").mkdir()
    reconstruction.write(str(tmp_path / "sparse"))
    monkeypatch.setenv("MONOLOC_DATA_DIR", str(tmp_path / "data"))
    code, _, err = run_monoloc(
        monkeypatch, capsys, "map", "import", "--format", "colmap", str(tmp_path / "sparse"),
        "--images", str(tmp_path / "images"), "--map", "fov",
    )  # fmt: skip
    assert code == 1 and err.count("\n") == 1 and "Traceback" not in err
    assert "camera 1: the camera model FOV is not one monoloc knows" in err
    code, out, _ = run_monoloc(monkeypatch, capsys, "map", "list")
    assert code == 0 and " fov " not in out

"""A query through a distorted lens (docs/method.md section 6): its keypoints are
undistorted with the camera's model before PnP, so a raw distorted frame localizes as
well as a pinhole frame of the same place; without the model it does not. The distorted
frames are the sim's fleet run: the query's drive rendered through issue 48's fleet
camera (1024x576, f 640 px, plumb_bob k1 -0.28, its own mounting; monoloc.sim.lens)."""

from __future__ import annotations

import numpy as np
import pytest
from sim_city import ingested_city, read_fleet_run

from monoloc.core.camera import CameraIntrinsics, LensDistortion
from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import planar_from_T_world_from_cam
from monoloc.server.vision.undistort import distort_pixels, undistort_pixels

PLUMB_BOB = LensDistortion("plumb_bob", (-0.28, 0.09, 0.0006, -0.0004))


@pytest.mark.parametrize(
    "lens",
    [
        PLUMB_BOB,
        LensDistortion("rational_polynomial", (-0.28, 0.09, 6e-4, -4e-4, 0.01, 0.02, 0.0, 0.0)),
        LensDistortion("fisheye", (0.05, -0.01, 0.002, 0.0)),
    ],
)
def test_undistortion_inverts_the_lens_model(lens):
    cam = CameraIntrinsics(640.0, 640.0, 511.5, 287.5, 1024, 576, lens)
    grid = np.stack(np.meshgrid(np.linspace(0, 1023, 9), np.linspace(0, 575, 7)), -1)
    ideal = grid.reshape(-1, 2)
    seen = distort_pixels(ideal, cam)
    assert np.abs(seen - ideal).max() > 20  # a real lens, not a no-op
    np.testing.assert_allclose(undistort_pixels(seen, cam), ideal, atol=1e-4)
    assert undistort_pixels(seen, cam.pinhole) is not None
    np.testing.assert_array_equal(undistort_pixels(seen, cam.pinhole), seen)


def test_lens_models_are_checked_and_named():
    assert LensDistortion("fisheye", (0.1, 0, 0, 0)).model == "equidistant"
    assert LensDistortion.parse("plumb_bob", [0, 0, 0, 0, 0]) is None  # zero D: a pinhole
    assert LensDistortion.parse("none", None) is None
    with pytest.raises(InvalidInputError, match="unknown lens distortion model 'kannala_x'"):
        LensDistortion("kannala_x", (0.1,))
    with pytest.raises(InvalidInputError, match="plumb_bob takes 4 or 5 coefficients"):
        LensDistortion("plumb_bob", (0.1, 0.2))
    with pytest.raises(InvalidInputError, match="without their model"):
        LensDistortion.parse(None, [0.1, 0.0, 0.0, 0.0])


@pytest.fixture(scope="module")
def city(tmp_path_factory):
    root = tmp_path_factory.mktemp("lens_city")
    registry, query_run = ingested_city(root, seed=5, frames=30, fleet=True)
    return registry, query_run, read_fleet_run(root)


def _errors(registry, frames, images, camera) -> list[float]:
    from monoloc.server.localize import LocalizeConfig

    out = []
    for frame, image in zip(frames, images, strict=True):
        result, _ = registry.localize(1, image, LocalizeConfig(), np.random.default_rng(3), camera)
        best = result.joint or result.best
        truth = planar_from_T_world_from_cam(frame.T_world_from_cam)
        out.append(np.inf if best is None else float(np.hypot(*(best.pose_world[:2] - truth[:2]))))
    return out


def test_a_distorted_query_localizes_like_its_pinhole_frame_and_only_with_its_model(city):
    registry, query_run, fleet_run = city
    lens = fleet_run.intrinsics
    assert lens.distortion == PLUMB_BOB
    # the same stretch of the same drive: the mapping camera's pinhole frames, the fleet
    # camera's distorted ones (each judged against its own camera's poses)
    frames, fleet_frames = query_run.frames[2:26:3], fleet_run.frames[2:26:3]
    plain = [query_run.load(f).image_gray for f in frames]
    distorted = [fleet_run.load(f).image_gray for f in fleet_frames]
    ours = np.median(_errors(registry, frames, plain, query_run.intrinsics))
    with_model = np.median(_errors(registry, fleet_frames, distorted, lens))
    without = np.median(_errors(registry, fleet_frames, distorted, lens.pinhole))
    print(f"\nmedian error: pinhole {ours:.3f} m, distorted {with_model:.3f} m, "
          f"distorted read as pinhole {without:.3f} m")  # fmt: skip
    assert ours < 0.3
    assert with_model <= 1.5 * ours + 0.03
    assert without > 2.0 * with_model + 0.05

"""The planar PnP pose covariance: against finite differences of OpenCV's projection, the
Monte Carlo spread of solvePnP under pixel noise, and what it is for (clustered vs
spread inliers)."""

import math

import cv2
import numpy as np
import pytest

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.server.vision.pose_covariance import planar_pose_covariance, position_spread_m

INTRINSICS = CameraIntrinsics(fx=718.0, fy=718.0, cx=620.0, cy=188.0, width_px=1241, height_px=376)


def camera_pose(yaw_rad: float = 0.3, centre=(2.0, -1.0, 1.6)) -> np.ndarray:
    """T_world_from_cam of a forward-looking car camera (z-up world, optical axis along
    the heading)."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    forward, left, up = np.array([c, s, 0.0]), np.array([-s, c, 0.0]), np.array([0, 0, 1.0])
    T = np.eye(4)
    T[:3, :3] = np.column_stack([-left, -up, forward])  # camera x right, y down, z forward
    T[:3, 3] = centre
    return T


def points_in_view(T_world_from_cam, n, rng, depth=(5.0, 30.0), spread_px=None, centre_px=None):
    """n world points seen by the camera: random pixels (over the image, or within
    ``spread_px`` of ``centre_px``) at random depths."""
    if spread_px is None:
        u = rng.uniform(40, INTRINSICS.width_px - 40, n)
        v = rng.uniform(20, INTRINSICS.height_px - 20, n)
    else:
        u = centre_px[0] + rng.uniform(-spread_px, spread_px, n)
        v = centre_px[1] + rng.uniform(-spread_px, spread_px, n)
    z = rng.uniform(*depth, n)
    p_cam = np.column_stack(
        [(u - INTRINSICS.cx) / INTRINSICS.fx * z, (v - INTRINSICS.cy) / INTRINSICS.fy * z, z]
    )
    return p_cam @ T_world_from_cam[:3, :3].T + T_world_from_cam[:3, 3]


def project(T_world_from_cam, points_world):
    T_cam_from_world = np.linalg.inv(T_world_from_cam)
    rvec = cv2.Rodrigues(T_cam_from_world[:3, :3])[0]
    pixels, _ = cv2.projectPoints(points_world, rvec, T_cam_from_world[:3, 3], INTRINSICS.K, None)
    return pixels.reshape(-1, 2)


def moved(T_world_from_cam, delta):
    """The camera moved by delta = (dX, dY, dZ, rot about world x, y, z through its centre)."""
    out = T_world_from_cam.copy()
    out[:3, 3] += delta[:3]
    out[:3, :3] = cv2.Rodrigues(np.asarray(delta[3:], dtype=np.float64))[0] @ out[:3, :3]
    return out


def test_matches_finite_differences_of_opencv_projection():
    rng = np.random.default_rng(0)
    T = camera_pose()
    points = points_in_view(T, 60, rng)
    base = project(T, points).ravel()
    h = 1e-6
    J = np.column_stack(
        [(project(moved(T, h * np.eye(6)[k]), points).ravel() - base) / h for k in range(6)]
    )
    expected = np.linalg.inv(J.T @ J)[np.ix_((0, 1, 5), (0, 1, 5))]
    got = planar_pose_covariance(T, points, INTRINSICS)
    np.testing.assert_allclose(got, expected, rtol=1e-3, atol=1e-12)


def test_predicts_the_spread_of_pnp_under_pixel_noise():
    """Monte Carlo: 1 px Gaussian noise on the pixels, SQPnP then LM, 400 trials; the
    empirical covariance of (X, Y, psi) matches the prediction within sampling error."""
    rng = np.random.default_rng(1)
    T = camera_pose()
    points = points_in_view(T, 40, rng)
    clean = project(T, points)
    poses = []
    for _ in range(400):
        noisy = clean + rng.normal(size=clean.shape)
        ok, rvec, tvec = cv2.solvePnP(points, noisy, INTRINSICS.K, None, flags=cv2.SOLVEPNP_SQPNP)
        rvec, tvec = cv2.solvePnPRefineLM(points, noisy, INTRINSICS.K, None, rvec, tvec)
        R = cv2.Rodrigues(rvec)[0]
        centre = -R.T @ tvec.ravel()
        forward = R.T[:, 2]
        poses.append([centre[0], centre[1], math.atan2(forward[1], forward[0])])
    empirical = np.cov(np.array(poses).T)
    predicted = planar_pose_covariance(T, points, INTRINSICS)
    for k in range(3):
        assert empirical[k, k] == pytest.approx(predicted[k, k], rel=0.2)
    # and the correlation between X and Y (the along-track axis dominates)
    corr_emp = empirical[0, 1] / math.sqrt(empirical[0, 0] * empirical[1, 1])
    corr_pred = predicted[0, 1] / math.sqrt(predicted[0, 0] * predicted[1, 1])
    assert corr_emp == pytest.approx(corr_pred, abs=0.15)


def test_inliers_clustered_on_one_object_pin_the_pose_down_far_less():
    """The same number of inliers: spread over the view and depths, or on one car-sized
    patch 14 m away (what a parked car that moved between the runs gives)."""
    rng = np.random.default_rng(2)
    T = camera_pose()
    spread = points_in_view(T, 50, rng)
    car = points_in_view(T, 50, rng, depth=(13.5, 15.0), spread_px=60, centre_px=(900, 250))
    spread_m = position_spread_m(planar_pose_covariance(T, spread, INTRINSICS))
    car_m = position_spread_m(planar_pose_covariance(T, car, INTRINSICS))
    assert car_m > 10 * spread_m


def test_scales_with_pixel_noise_and_point_count():
    rng = np.random.default_rng(3)
    T = camera_pose()
    points = points_in_view(T, 30, rng)
    one = planar_pose_covariance(T, points, INTRINSICS)
    np.testing.assert_allclose(planar_pose_covariance(T, points, INTRINSICS, 2.0), 4 * one)
    twice = planar_pose_covariance(T, np.concatenate([points, points]), INTRINSICS)
    np.testing.assert_allclose(twice, one / 2, rtol=1e-9)
    assert np.all(np.linalg.eigvalsh(one) > 0)
    np.testing.assert_allclose(one, one.T)


def test_keypoint_scales_weigh_each_point_by_its_pyramid_level():
    """A keypoint of scale s counts as s px of noise: every point at scale 2 is 2 px of
    noise everywhere; coarse points added to fine ones inform the pose less than the
    same points at full resolution, and more than none."""
    rng = np.random.default_rng(5)
    T = camera_pose()
    fine, coarse = points_in_view(T, 30, rng), points_in_view(T, 30, rng)
    one = planar_pose_covariance(T, fine, INTRINSICS)
    np.testing.assert_allclose(
        planar_pose_covariance(T, fine, INTRINSICS, keypoint_scales=np.full(30, 2.0)),
        planar_pose_covariance(T, fine, INTRINSICS, 2.0),
        rtol=1e-9,
    )
    both = np.concatenate([fine, coarse])
    scales = np.concatenate([np.ones(30), np.full(30, 1.2**5)])
    weighed = planar_pose_covariance(T, both, INTRINSICS, keypoint_scales=scales)
    unweighed = planar_pose_covariance(T, both, INTRINSICS)
    assert position_spread_m(unweighed) < position_spread_m(weighed) < position_spread_m(one)


def test_keypoint_scales_predict_the_spread_of_pnp_under_level_dependent_noise():
    """Monte Carlo as above, each pixel's noise s px for its point's scale s (a quarter of
    the points at full resolution, the rest at ORB's level 7, as on a night frame): the
    weighed covariance matches the empirical one, the unweighed one at 1 px is about a
    third of it."""
    rng = np.random.default_rng(6)
    T = camera_pose()
    points = points_in_view(T, 40, rng)
    scales = np.where(np.arange(40) % 4 == 0, 1.0, 1.2**7)
    clean = project(T, points)
    positions = []
    for _ in range(400):
        noisy = clean + rng.normal(size=clean.shape) * scales[:, None]
        ok, rvec, tvec = cv2.solvePnP(points, noisy, INTRINSICS.K, None, flags=cv2.SOLVEPNP_SQPNP)
        # the maximum-likelihood pose under this noise: each residual over its own std
        # (OpenCV's LM has no weights; a few Gauss-Newton steps on the scaled residuals)
        for _ in range(5):
            R = cv2.Rodrigues(rvec)[0]
            proj, jac = cv2.projectPoints(points, rvec, tvec, INTRINSICS.K, None)
            w = np.repeat(1.0 / scales, 2)[:, None]
            r = (noisy - proj.reshape(-1, 2)).ravel()[:, None] * w
            J = jac[:, :6] * w
            step = np.linalg.lstsq(J, r, rcond=None)[0].ravel()
            rvec, tvec = rvec + step[:3, None], tvec + step[3:, None]
        R = cv2.Rodrigues(rvec)[0]
        positions.append((-R.T @ tvec.ravel())[:2])
    empirical = np.cov(np.array(positions).T)
    weighed = planar_pose_covariance(T, points, INTRINSICS, keypoint_scales=scales)
    unweighed = planar_pose_covariance(T, points, INTRINSICS)
    for k in range(2):
        assert empirical[k, k] == pytest.approx(weighed[k, k], rel=0.2)
    assert np.trace(unweighed[:2, :2]) < 0.5 * np.trace(empirical[:2, :2])


@pytest.mark.parametrize("scales", [np.ones(4), np.array([1.0] * 9 + [0.0]), np.full(10, np.nan)])
def test_bad_keypoint_scales_are_refused(scales):
    rng = np.random.default_rng(7)
    T = camera_pose()
    with pytest.raises(InvalidInputError):
        planar_pose_covariance(T, points_in_view(T, 10, rng), INTRINSICS, keypoint_scales=scales)


def test_too_few_points_in_front_give_none():
    rng = np.random.default_rng(4)
    T = camera_pose()
    points = points_in_view(T, 3, rng)
    assert planar_pose_covariance(T, points, INTRINSICS) is None
    behind = 2 * T[:3, 3] - points_in_view(T, 10, rng)  # mirrored through the centre
    assert planar_pose_covariance(T, behind, INTRINSICS) is None
    assert math.isnan(position_spread_m(None))


@pytest.mark.parametrize(
    "T, points, std",
    [
        (np.eye(3), np.zeros((5, 3)), 1.0),
        (np.eye(4), np.zeros((5, 2)), 1.0),
        (np.eye(4), np.zeros((5, 3)), 0.0),
    ],
)
def test_bad_input_is_refused(T, points, std):
    with pytest.raises(InvalidInputError):
        planar_pose_covariance(T, points, INTRINSICS, std)

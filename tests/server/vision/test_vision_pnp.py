import cv2
import numpy as np
import pytest

from monoloc.core.camera import KITTI_CAM0 as CAM
from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import invert_rigid, rotation_angle_rad
from monoloc.server.vision.pnp import PnpConfig, estimate_relative_pose, within_threshold


def _rotation(axis, angle_rad):
    axis = np.asarray(axis, dtype=np.float64)
    return cv2.Rodrigues(axis / np.linalg.norm(axis) * angle_rad)[0]


def _scene(rng, n=300, outlier_fraction=0.3, noise_px=0.5, T_ref_from_query=None):
    """Query pixels (n, 2) of points 5-40 m ahead, the points in the reference frame, the
    true T_ref_from_query and the outlier mask (outliers get a random pixel)."""
    pixels = np.stack(
        [rng.uniform(0, CAM.width_px - 1, n), rng.uniform(0, CAM.height_px - 1, n)], axis=1
    )
    depth = rng.uniform(5.0, 40.0, n)
    points_query_cam = np.stack(
        [(pixels[:, 0] - CAM.cx) / CAM.fx * depth, (pixels[:, 1] - CAM.cy) / CAM.fy * depth, depth],
        axis=1,
    )
    if T_ref_from_query is None:
        T_ref_from_query = np.eye(4)
        T_ref_from_query[:3, :3] = _rotation(rng.normal(size=3), np.radians(rng.uniform(0, 20)))
        T_ref_from_query[:3, 3] = rng.uniform(-3.0, 3.0, 3)
    points_ref_cam = points_query_cam @ T_ref_from_query[:3, :3].T + T_ref_from_query[:3, 3]
    observed = pixels + rng.normal(0.0, noise_px, pixels.shape)
    outliers = rng.random(n) < outlier_fraction
    observed[outliers] = np.stack(
        [
            rng.uniform(0, CAM.width_px - 1, outliers.sum()),
            rng.uniform(0, CAM.height_px - 1, outliers.sum()),
        ],
        axis=1,
    )
    return observed, points_ref_cam, T_ref_from_query, outliers


def _errors(T_true, T_est):
    delta = invert_rigid(T_true) @ T_est
    return np.linalg.norm(delta[:3, 3]), np.degrees(rotation_angle_rad(delta[:3, :3]))


@pytest.mark.parametrize("seed", range(10))
def test_round_trip_with_noise_and_outliers_recovers_the_pose(seed):
    observed, points_ref, T_true, outliers = _scene(np.random.default_rng(seed))
    result = estimate_relative_pose(
        observed, points_ref, CAM, PnpConfig(), np.random.default_rng(seed)
    )
    assert result.accepted, result.reject_reason
    assert result.T_ref_from_query.shape == (4, 4)
    error_m, error_deg = _errors(T_true, result.T_ref_from_query)
    assert error_m < 0.01 and error_deg < 0.1
    # Inliers are the true correspondences (a random outlier may land within 3 px).
    assert result.inlier_mask.shape == (len(observed),) and result.inlier_mask.dtype == bool
    assert np.mean(result.inlier_mask == ~outliers) > 0.98
    assert result.n_inliers == result.inlier_mask.sum()
    assert 0.3 < result.reprojection_error_px < 1.0  # 0.5 px noise per axis: mean ~0.63 px


@pytest.mark.parametrize("seed", range(10))
def test_points_on_one_wall_are_not_a_problem(seed):
    # Coplanar points: OpenCV's own refit after P3P RANSAC (EPnP) was measured up to 14 m
    # and 53 deg off on exactly this scene; the SQPnP refit must keep it accurate.
    rng = np.random.default_rng(seed)
    n = 300
    pixels = np.stack(
        [rng.uniform(0, CAM.width_px - 1, n), rng.uniform(0, CAM.height_px - 1, n)], 1
    )
    rays = np.stack(
        [(pixels[:, 0] - CAM.cx) / CAM.fx, (pixels[:, 1] - CAM.cy) / CAM.fy, np.ones(n)], 1
    )
    normal = np.array([0.5, 0.0, 1.0]) / np.linalg.norm([0.5, 0.0, 1.0])
    points_query_cam = rays * (12.0 / (rays @ normal))[:, None]  # wall 12 m away, turned 27 deg
    T_true = np.eye(4)
    T_true[:3, :3] = _rotation(rng.normal(size=3), np.radians(rng.uniform(0, 10)))
    T_true[:3, 3] = rng.uniform(-2.0, 2.0, 3)
    points_ref = points_query_cam @ T_true[:3, :3].T + T_true[:3, 3]
    observed = pixels + rng.normal(0.0, 0.5, pixels.shape)
    outliers = rng.random(n) < 0.3
    observed[outliers] = observed[rng.permutation(np.flatnonzero(outliers))]
    result = estimate_relative_pose(observed, points_ref, CAM, PnpConfig(), rng)
    assert result.accepted, result.reject_reason
    error_m, error_deg = _errors(T_true, result.T_ref_from_query)
    assert error_m < 0.03 and error_deg < 0.15


@pytest.mark.parametrize("seed", range(5))
def test_unrelated_points_or_shuffled_matches_are_rejected(seed):
    rng = np.random.default_rng(seed)
    observed, points_ref, _, _ = _scene(rng, outlier_fraction=0.0)
    shuffled = points_ref[rng.permutation(len(points_ref))]
    _, unrelated, _, _ = _scene(rng)
    for points in (shuffled, unrelated):
        result = estimate_relative_pose(observed, points, CAM, PnpConfig(), rng)
        assert not result.accepted and result.reject_reason
        assert result.n_inliers < PnpConfig().min_inliers


def test_rotation_beyond_the_field_of_view_is_rejected():
    T_ref_from_query = np.eye(4)
    T_ref_from_query[:3, :3] = _rotation([0, 1, 0], np.radians(100.0))  # FOV is ~81.6 deg
    T_ref_from_query[:3, 3] = [1.0, 0.0, 2.0]
    observed, points_ref, _, _ = _scene(np.random.default_rng(0), T_ref_from_query=T_ref_from_query)
    result = estimate_relative_pose(
        observed, points_ref, CAM, PnpConfig(), np.random.default_rng(0)
    )
    assert not result.accepted and "rotation" in result.reject_reason
    # The pose itself was found: the rejection is the FOV rule, not a failure.
    assert _errors(T_ref_from_query, result.T_ref_from_query)[1] < 0.1
    wide = PnpConfig(max_rotation_rad=np.radians(120.0))
    assert estimate_relative_pose(
        observed, points_ref, CAM, wide, np.random.default_rng(0)
    ).accepted


def test_min_inliers_rule_and_too_few_correspondences():
    observed, points_ref, _, _ = _scene(np.random.default_rng(3), n=20, outlier_fraction=0.0)
    rng = np.random.default_rng(0)
    assert estimate_relative_pose(
        observed, points_ref, CAM, PnpConfig(min_inliers=15), rng
    ).accepted
    result = estimate_relative_pose(observed, points_ref, CAM, PnpConfig(min_inliers=25), rng)
    assert not result.accepted and "too few correspondences" in result.reject_reason
    assert np.all(np.isnan(result.T_ref_from_query))
    # 20 correspondences, 8 of them wrong: 12 inliers < 15.
    observed[:8] = observed[8:16][::-1] + 50.0
    result = estimate_relative_pose(observed, points_ref, CAM, PnpConfig(min_inliers=15), rng)
    assert not result.accepted and "min_inliers" in result.reject_reason
    assert 10 <= result.n_inliers < 15


def test_same_rng_same_result():
    observed, points_ref, _, _ = _scene(np.random.default_rng(1), outlier_fraction=0.5)
    config = PnpConfig(refine=False, iterations=100)
    a = estimate_relative_pose(observed, points_ref, CAM, config, np.random.default_rng(7))
    b = estimate_relative_pose(observed, points_ref, CAM, config, np.random.default_rng(7))
    assert a.accepted
    assert np.array_equal(a.T_ref_from_query, b.T_ref_from_query)
    assert np.array_equal(a.inlier_mask, b.inlier_mask)


def test_degenerate_and_malformed_inputs():
    rng = np.random.default_rng(0)
    same_point = estimate_relative_pose(
        np.full((30, 2), 100.0), np.tile([0.0, 0.0, 10.0], (30, 1)), CAM, PnpConfig(), rng
    )
    assert not same_point.accepted
    with pytest.raises(InvalidInputError):
        estimate_relative_pose(np.zeros((10, 3)), np.zeros((10, 3)), CAM, PnpConfig(), rng)
    with pytest.raises(InvalidInputError):
        estimate_relative_pose(np.zeros((10, 2)), np.zeros((9, 3)), CAM, PnpConfig(), rng)
    with pytest.raises(InvalidInputError):
        estimate_relative_pose(np.full((10, 2), np.nan), np.zeros((10, 3)), CAM, PnpConfig(), rng)


def test_compiled_lm_reaches_opencvs_lm_optimum_and_scores_like_projectpoints():
    from monoloc.server.vision._pnp_kernel import inlier_errors, refine_lm

    rng = np.random.default_rng(7)
    pixels, points, T_ref_from_query, outliers = _scene(rng, n=400, outlier_fraction=0.0)
    T_query_from_ref = invert_rigid(T_ref_from_query)
    # Start 2 deg and 0.3 m away from the truth.
    R0 = _rotation([0.3, 1.0, -0.2], np.radians(2.0)) @ T_query_from_ref[:3, :3]
    t0 = T_query_from_ref[:3, 3] + [0.3, -0.1, 0.2]
    mask = np.ones(len(points), dtype=bool)
    K = CAM.K
    args = (K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    errors_px, inliers = np.empty(len(points)), np.empty(len(points), dtype=bool)
    projected, _ = cv2.projectPoints(points, cv2.Rodrigues(R0)[0], t0, K, None)
    expected_px = np.linalg.norm(projected[:, 0] - pixels, axis=1)
    threshold_px = float(np.median(expected_px))  # half the points inside
    inlier_errors(points, pixels, R0, t0, *args, threshold_px, errors_px, inliers)
    assert np.allclose(errors_px, expected_px, atol=1e-6)
    in_front = (points @ R0.T + t0)[:, 2] > 0
    assert np.array_equal(inliers, (errors_px <= threshold_px) & in_front)
    assert 0 < inliers.sum() < len(points)

    ones = np.ones(len(points))
    R, t, cost = refine_lm(points, pixels, mask, ones, R0, t0, *args, 20)
    rvec_cv, tvec_cv = cv2.solvePnPRefineLM(
        points,
        pixels,
        K,
        None,
        cv2.Rodrigues(R0)[0],
        t0.reshape(3, 1).copy(),
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12),
    )
    assert np.allclose(cv2.Rodrigues(R)[0].ravel(), rvec_cv.ravel(), atol=1e-7)
    assert np.allclose(t, tvec_cv.ravel(), atol=1e-5)
    # 0.5 px noise: the optimum sits near the truth, and far below the starting cost.
    assert np.linalg.norm(t - T_query_from_ref[:3, 3]) < 0.05
    inlier_errors(points, pixels, R, t, *args, threshold_px, errors_px, inliers)
    assert cost == pytest.approx(float(np.sum(errors_px**2)), rel=1e-9)
    assert np.sqrt(cost / len(points)) < 1.0
    # Masked-out points do not pull the fit: corrupt them and the result stays.
    corrupted = pixels.copy()
    corrupted[:50] += 40.0
    mask[:50] = False
    R2, t2, _ = refine_lm(points, corrupted, mask, ones, R0, t0, *args, 20)
    assert np.linalg.norm(t2 - t) < 0.02
    assert np.degrees(rotation_angle_rad(R2 @ R.T)) < 0.05


def test_lm_weights_are_inverse_variances():
    from monoloc.server.vision._pnp_kernel import refine_lm

    rng = np.random.default_rng(11)
    pixels, points, T_ref_from_query, _ = _scene(rng, n=300, outlier_fraction=0.0)
    T_query_from_ref = invert_rigid(T_ref_from_query)
    R0 = _rotation([0.2, -1.0, 0.4], np.radians(1.0)) @ T_query_from_ref[:3, :3]
    t0 = T_query_from_ref[:3, 3] + [0.2, 0.1, -0.2]
    K = CAM.K
    args = (K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    corrupted = pixels.copy()
    corrupted[:60] += 25.0
    all_points = np.ones(len(points), dtype=bool)
    masked = all_points.copy()
    masked[:60] = False
    ones = np.ones(len(points))
    R_masked, t_masked, _ = refine_lm(points, corrupted, masked, ones, R0, t0, *args, 30)
    # A weight of (almost) zero leaves a point out as the mask does ...
    nearly_out = ones.copy()
    nearly_out[:60] = 1e-12
    R_w, t_w, _ = refine_lm(points, corrupted, all_points, nearly_out, R0, t0, *args, 30)
    assert np.linalg.norm(t_w - t_masked) < 1e-4
    assert np.degrees(rotation_angle_rad(R_w @ R_masked.T)) < 1e-3
    # ... with unit weights the corrupted points pull the pose away ...
    R_u, t_u, _ = refine_lm(points, corrupted, all_points, ones, R0, t0, *args, 30)
    assert np.linalg.norm(t_u - t_masked) > 0.01
    # ... an empty weights array stands for all 1 ...
    R_e, t_e, cost_e = refine_lm(points, corrupted, masked, np.empty(0), R0, t0, *args, 30)
    R_1, t_1, cost_1 = refine_lm(points, corrupted, masked, ones, R0, t0, *args, 30)
    assert np.array_equal(t_e, t_1) and np.array_equal(R_e, R_1) and cost_e == cost_1
    # ... and scaling every weight alike changes the cost, not the optimum.
    R_s, t_s, cost_s = refine_lm(points, corrupted, masked, 4.0 * ones, R0, t0, *args, 30)
    assert np.linalg.norm(t_s - t_masked) < 1e-6


@pytest.mark.parametrize("seed", range(5))
def test_usac_recovers_the_pose_reproducibly_and_like_the_classic_ransac(seed):
    observed, points_ref, T_true, outliers = _scene(np.random.default_rng(seed))
    usac = PnpConfig(ransac="usac")
    first = estimate_relative_pose(observed, points_ref, CAM, usac, np.random.default_rng(seed))
    again = estimate_relative_pose(observed, points_ref, CAM, usac, np.random.default_rng(seed))
    classic = estimate_relative_pose(
        observed, points_ref, CAM, PnpConfig(), np.random.default_rng(seed)
    )
    assert first.accepted and classic.accepted
    error_m, error_deg = _errors(T_true, first.T_ref_from_query)
    assert error_m < 0.01 and error_deg < 0.1
    assert np.array_equal(first.T_ref_from_query, again.T_ref_from_query)
    assert abs(first.n_inliers - classic.n_inliers) <= 2
    assert np.mean(first.inlier_mask == ~outliers) > 0.98
    # and unrelated points are still no pose
    shuffled = np.random.default_rng(seed).permutation(len(points_ref))
    junk = estimate_relative_pose(
        observed, points_ref[shuffled], CAM, usac, np.random.default_rng(seed)
    )
    assert not junk.accepted


def test_unknown_ransac_method_is_refused():
    with pytest.raises(InvalidInputError, match="ransac"):
        PnpConfig(ransac="magic")


def _refine_step_by_step(points, pixels, R, t, K, config, rounds, candidates):
    """refine_from_pose's rounds written out with the single-step kernels (what the
    compiled refine_rounds replaced): inliers, LM, inliers, ..."""
    from monoloc.server.vision._pnp_kernel import inlier_errors, refine_lm

    def select(R, t):
        errors, mask = np.empty(len(points)), np.empty(len(points), dtype=bool)
        inlier_errors(points, pixels, R, t, *K[[0, 1, 0, 1], [0, 1, 2, 2]],
                      config.reprojection_error_px, errors, mask)  # fmt: skip
        return (mask & candidates if candidates is not None else mask), errors

    mask, errors = select(R, t)
    for _ in range(rounds):
        if mask.sum() < 6:
            return None, None, mask, errors
        R, t, _ = refine_lm(points, pixels, mask, np.empty(0), R, t,
                            *K[[0, 1, 0, 1], [0, 1, 2, 2]], config.refine_iterations)  # fmt: skip
        mask, errors = select(R, t)
    return R, t, mask, errors


@pytest.mark.parametrize("seed", range(3))
def test_compiled_refine_rounds_equals_the_step_by_step_refit(seed):
    from monoloc.server.vision.pnp import refine_from_pose

    rng = np.random.default_rng(seed)
    pixels, points, T_true, _ = _scene(rng, outlier_fraction=0.3, noise_px=0.7)
    T_query_from_ref = invert_rigid(T_true)
    R0 = _rotation(rng.normal(size=3), np.radians(0.05)) @ T_query_from_ref[:3, :3]
    t0 = T_query_from_ref[:3, 3] + rng.normal(0, 0.01, 3)
    config = PnpConfig()
    solved = 0
    for candidates in (None, rng.random(len(points)) < 0.8):
        for rounds in (1, 2, 3):
            got = refine_from_pose(points, pixels, R0, t0, CAM.K, config, rounds, candidates)
            want = _refine_step_by_step(points, pixels, R0, t0, CAM.K, config, rounds, candidates)
            np.testing.assert_array_equal(got[2], want[2])
            np.testing.assert_allclose(got[3], want[3], rtol=0, atol=1e-12)
            assert (got[0] is None) == (want[0] is None)
            if want[0] is not None:
                solved += 1
                np.testing.assert_allclose(got[0], want[0], rtol=0, atol=1e-12)
                np.testing.assert_allclose(got[1], want[1], rtol=0, atol=1e-12)
    assert solved >= 3  # the start is close enough for most settings to refine
    # too few inliers to refine on: no pose, the selection as it stood
    few = np.zeros(len(points), dtype=bool)
    few[:5] = True
    R, t, mask, _ = refine_from_pose(points, pixels, R0, t0, CAM.K, config, 2, few)
    assert R is None and t is None and mask.sum() <= 5


def test_within_threshold_is_pnps_inlier_test_under_a_given_pose():
    """The true pose keeps the clean correspondences and drops the random pixels (and
    the points it puts behind the camera); a pose a metre off keeps few of them."""
    rng = np.random.default_rng(11)
    pixels, points_ref, T_ref_from_query, outliers = _scene(rng, noise_px=0.3)
    T_query_from_ref = invert_rigid(T_ref_from_query)
    inside = within_threshold(pixels, points_ref, T_query_from_ref, CAM, 3.0)
    assert inside[~outliers].all()
    assert inside[outliers].mean() < 0.05
    behind = points_ref.copy()
    behind[:10] = 2 * T_ref_from_query[:3, 3] - behind[:10]  # mirrored through the centre
    assert not within_threshold(pixels, behind, T_query_from_ref, CAM, 3.0)[:10].any()
    moved = T_query_from_ref.copy()
    moved[0, 3] += 1.0
    assert within_threshold(pixels, points_ref, moved, CAM, 3.0)[~outliers].mean() < 0.3


def _tailed_scene(seed, tail_fraction=0.2, n=400):
    """Correspondences nearly all within PnP's 3 px threshold, shaped as the sim's ORB
    inliers are: Gaussian errors of 0.4 px times the keypoint's pyramid scale (1-2), and a
    tail of ``tail_fraction`` off by a further 1.5-2.8 px in a random direction (a corner
    found a little elsewhere)."""
    rng = np.random.default_rng(seed)
    observed, points_ref, T_true, _ = _scene(rng, n=n, outlier_fraction=0.0, noise_px=0.0)
    scales = rng.choice([1.0, 1.2, 1.44, 1.728, 2.0736], n)
    observed += rng.normal(0.0, 0.4, (n, 2)) * scales[:, None]
    tail = rng.random(n) < tail_fraction
    angle = rng.uniform(0, 2 * np.pi, tail.sum())
    size = rng.uniform(1.5, 2.8, tail.sum())
    observed[tail] += np.stack([np.cos(angle), np.sin(angle)], axis=1) * size[:, None]
    T_query_from_ref = invert_rigid(T_true)
    return observed, points_ref, T_true, T_query_from_ref, scales


def test_robust_refit_fades_out_a_tail_of_near_inliers():
    from monoloc.server.vision.pnp import refine_from_pose, robust_refit

    config = PnpConfig()
    plain_m, robust_m = [], []
    for seed in range(24):
        observed, points_ref, T_true, T_qr, scales = _tailed_scene(seed)
        R, t, mask, _ = refine_from_pose(
            points_ref, observed, T_qr[:3, :3].copy(), T_qr[:3, 3].copy(), CAM.K, config, 2
        )
        assert mask.mean() > 0.9  # the tail is within the threshold: inliers nearly all
        R_r, t_r, errors_px = robust_refit(
            points_ref, observed, mask, R, t, CAM.K, config, scales, 2.385, 3
        )
        assert errors_px.shape == (len(observed),)
        for (Rx, tx), out in (((R, t), plain_m), ((R_r, t_r), robust_m)):
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = Rx, tx
            out.append(_errors(T_true, invert_rigid(T))[0])
    # least squares lets the tail pull; the Cauchy weights fade it (0.83x the mean, 0.68x
    # the median error here)
    assert np.mean(robust_m) < 0.9 * np.mean(plain_m)
    assert np.median(robust_m) < 0.8 * np.median(plain_m)


def test_robust_refit_keeps_an_exact_pose_and_ignores_a_uniform_scale():
    from monoloc.server.vision.pnp import robust_refit

    config = PnpConfig()
    rng = np.random.default_rng(3)
    observed, points_ref, T_true, _ = _scene(rng, n=200, outlier_fraction=0.0, noise_px=0.0)
    T_qr = invert_rigid(T_true)
    mask = np.ones(len(observed), dtype=bool)
    R, t, _ = robust_refit(
        points_ref, observed, mask, T_qr[:3, :3], T_qr[:3, 3], CAM.K, config,
        np.ones(len(observed)), 2.385, 3,
    )  # fmt: skip
    np.testing.assert_allclose(R, T_qr[:3, :3], atol=1e-9)
    np.testing.assert_allclose(t, T_qr[:3, 3], atol=1e-7)
    # every keypoint at one scale: the same pose as at scale 1
    observed, points_ref, _, T_qr, _ = _tailed_scene(5)
    start = (T_qr[:3, :3] @ _rotation([0, 1, 0], 0.002), T_qr[:3, 3] + 0.01)
    mask = np.ones(len(observed), dtype=bool)
    one = robust_refit(points_ref, observed, mask, *start, CAM.K, config, np.ones(400), 2.385, 3)
    two = robust_refit(
        points_ref, observed, mask, *start, CAM.K, config, np.full(400, 2.0), 2.385, 3
    )
    np.testing.assert_allclose(one[0], two[0], atol=1e-9)
    np.testing.assert_allclose(one[1], two[1], atol=1e-7)


def test_robust_refit_rejects_bad_arguments():
    from monoloc.server.vision.pnp import robust_refit

    observed, points_ref, _, T_qr, scales = _tailed_scene(1, n=50)
    mask = np.ones(50, dtype=bool)
    args = (points_ref, observed, mask, T_qr[:3, :3], T_qr[:3, 3], CAM.K, PnpConfig())
    for bad_scales, c, rounds in (
        (scales[:-1], 2.385, 3),  # one scale short
        (np.where(np.arange(50) == 0, 0.0, scales), 2.385, 3),  # a zero scale
        (scales, 0.0, 3),
        (scales, float("nan"), 3),
        (scales, 2.385, 0),
    ):
        with pytest.raises(InvalidInputError):
            robust_refit(*args, bad_scales, c, rounds)
    with pytest.raises(InvalidInputError):
        robust_refit(*args[:2], np.zeros(50, dtype=bool), *args[3:], scales, 2.385, 3)

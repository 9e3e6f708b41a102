"""The Gaussian filter riding on the particles' mode (monoloc.client.refine): its motion
covariance is what sampling the signals' noise gives, it averages noisy hypotheses over
time better than the particles' mode, learns the speed signal's scale and the yaw-rate
signal's bias, ignores hypotheses outside its gate and its restart tolerance, follows
the particles when they move elsewhere, and adds no sideways bias in a steady turn."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from monoloc.client.motion import advance
from monoloc.client.particle_filter import FilterConfig, ParticleFilter
from monoloc.client.refine import ModeRefiner, RefineConfig
from monoloc.core.errors import InvalidInputError
from monoloc.core.measurement import Hypotheses, MeasurementModel, PnpCovarianceModel

DT_S = 0.1
SIGMA_M = 0.03  # the hypotheses' position noise (1 sigma per axis)
MODEL = MeasurementModel(Sigma1=np.diag([SIGMA_M**2, SIGMA_M**2, math.radians(0.2) ** 2]))


def _drive(n: int, speed_mps: float = 9.0, yaw_rate_radps: float = 0.0) -> np.ndarray:
    """True camera poses (n, 3) of a drive at constant speed and yaw rate."""
    poses = [np.array([5.0, -3.0, 0.4])]
    for _ in range(n - 1):
        poses.append(advance(poses[-1][None], speed_mps, yaw_rate_radps, DT_S)[0])
    return np.array(poses)


def _hypotheses(pose: np.ndarray, rng: np.random.Generator, offset_m=(0.0, 0.0)) -> Hypotheses:
    """Three hypotheses around the pose, each with its own noise; the first is the joint."""
    poses = pose + rng.normal(0, [SIGMA_M, SIGMA_M, math.radians(0.2)], size=(3, 3))
    poses[:, :2] += offset_m
    return Hypotheses(
        poses,
        poses.copy(),
        np.full(3, 0.9),
        n_inliers=np.array([300, 120, 80]),
        reprojection_error_px=np.ones(3),
        joint=np.array([True, False, False]),
    )


def _run(config: FilterConfig, truth: np.ndarray, measured_speed_mps: float, seed: int = 0):
    """Estimates (n, 3) and the filter after driving ``truth`` with the given speed signal
    and noisy hypotheses every frame."""
    pf = ParticleFilter(config, MODEL, np.random.default_rng(seed))
    hyp_rng = np.random.default_rng(100 + seed)
    out = np.full((len(truth), 3), np.nan)
    for i, pose in enumerate(truth):
        dt = DT_S if i else 0.0
        est = pf.step(dt, measured_speed_mps, 0.0, _hypotheses(pose, hyp_rng))
        if est is not None:
            out[i] = est.pose_world
    return out, pf


def test_the_predicted_covariance_is_what_sampling_the_signal_noise_gives():
    config = RefineConfig(
        position_noise_m=0.0,
        speed_scale_walk=0.0,
        heading_offset_walk_rad=0.0,
        yaw_rate_bias_walk_radps=0.0,
    )
    refiner = ModeRefiner(config)
    start_world = np.array([1.0, 2.0, 0.3])
    start_std = np.array([0.01, 0.02, 0.003])
    refiner.start(start_world, np.diag(start_std**2))
    speed, yaw_rate, lever = 8.0, 0.4, 1.2
    refiner.predict(DT_S, speed, yaw_rate, lever)
    # Monte Carlo: draw the start, k, b, g and the signals' noise; the car drives along the
    # reported heading minus b, turning at the measured yaw rate minus g; move each draw
    # exactly
    rng = np.random.default_rng(3)
    n = 200_000
    start = start_world + rng.normal(size=(n, 3)) * start_std
    scale = 1.0 + config.speed_scale_std * rng.normal(size=n)
    b = config.heading_offset_std_rad * rng.normal(size=n)
    bias = config.yaw_rate_bias_std_radps * rng.normal(size=n)
    start[:, 2] -= b
    v = (speed + config.speed_noise_mps * rng.normal(size=n)) * scale
    g = yaw_rate - bias + config.yaw_rate_noise_radps * rng.normal(size=n)
    moved = advance(start, v, g, DT_S, lever)
    sampled = np.cov(np.column_stack([moved, scale, b, bias]).T)
    # entry by entry within 3 % of the scale sqrt(C_ii C_jj) (sampling error ~0.3 %)
    scale_ij = np.sqrt(np.outer(np.diag(sampled), np.diag(sampled)))
    assert np.all(np.abs(refiner.covariance - sampled) <= 0.03 * scale_ij)
    np.testing.assert_allclose(refiner.state[:3], moved.mean(axis=0), atol=2e-4)


def _coast_after_hypotheses(config: FilterConfig, bias_radps: float, seed: int):
    """A straight drive at 9 m/s whose yaw-rate signal reads ``bias_radps`` high:
    hypotheses for 12 s, then none for 3 s. The filter and the position error (m) at the
    end of the gap."""
    n_seen, n_gap = 120, 30
    truth = _drive(n_seen + n_gap)
    pf = ParticleFilter(config, MODEL, np.random.default_rng(seed))
    rng = np.random.default_rng(50 + seed)
    for i, pose in enumerate(truth):
        seen = _hypotheses(pose, rng) if i < n_seen else Hypotheses.empty()
        est = pf.step(DT_S if i else 0.0, 9.0, bias_radps, seen)
    return pf, float(np.linalg.norm(est.pose_world[:2] - truth[-1, :2]))


def test_it_learns_the_yaw_rate_bias_and_coasts_straight_through_a_gap():
    """A gyro offset of 0.25 deg/s turns a dead-reckoned heading by 0.75 deg in a 3 s gap
    without hypotheses: 0.18 m of sideways drift at 9 m/s. Learnt from the hypotheses
    before the gap, the bias is taken off and the refined pose coasts straight."""
    bias = math.radians(0.25)
    config = FilterConfig(n_particles=500)
    without = replace(
        config, refine=RefineConfig(yaw_rate_bias_std_radps=0.0, yaw_rate_bias_walk_radps=0.0)
    )
    learnt, unlearnt = [], []
    for seed in range(2):
        pf, error_m = _coast_after_hypotheses(config, bias, seed)
        assert pf.refiner.yaw_rate_bias_radps == pytest.approx(bias, abs=0.3 * bias)
        learnt.append(error_m)
        unlearnt.append(_coast_after_hypotheses(without, bias, seed)[1])
    # learnt 0.03-0.09 m, without the bias term 0.18-0.29 m on seeds 0-3
    assert max(learnt) < 0.1, learnt
    assert max(learnt) < 0.5 * min(unlearnt), (learnt, unlearnt)


def test_a_hypothesis_beyond_the_restart_tolerance_is_not_used_whatever_its_spread():
    """Metres off with a covariance of metres, a hypothesis passes a Mahalanobis gate;
    beyond the restart tolerance it is not used: the pose and heading do not move."""
    refiner = ModeRefiner(RefineConfig())
    refiner.start(np.zeros(3), np.diag([0.05**2, 0.05**2, 0.003**2]))
    before = refiner.pose_world.copy()
    far = np.array([2.0, -1.5, math.radians(3.0)])
    wide = np.diag([1.0**2, 1.0**2, math.radians(2.0) ** 2])
    squared = far @ np.linalg.solve(wide + refiner.covariance[:3, :3], far)
    assert squared < RefineConfig().gate_mahalanobis_sq  # the Mahalanobis gate alone passes it
    assert not refiner._correct_one(far, wide)
    np.testing.assert_array_equal(refiner.pose_world, before)
    # within the tolerance, the same spread is used
    assert refiner._correct_one(np.array([0.3, -0.2, math.radians(1.0)]), wide)


def test_it_averages_noisy_hypotheses_better_than_the_particles_and_learns_the_speed_scale():
    """A straight drive whose speed signal reads 3 % low, three hypotheses with 3 cm of
    noise each frame: the refined pose is much closer to the truth than the particles'
    mode (which forgets the previous frames under its broad motion noise)."""
    truth = _drive(150)
    measured = 9.0 / 1.03
    late = slice(50, None)
    rms = {"refined": [], "mode": []}
    for seed in range(3):
        refined, pf = _run(FilterConfig(n_particles=500), truth, measured, seed)
        mode, _ = _run(FilterConfig(n_particles=500, refine=None), truth, measured, seed)
        for name, est in (("refined", refined), ("mode", mode)):
            squared = np.sum((est[late, :2] - truth[late, :2]) ** 2, axis=1)
            rms[name].append(float(np.sqrt(np.mean(squared))))
        assert pf.refiner.speed_scale == pytest.approx(1.03, abs=0.005)
    assert np.mean(rms["refined"]) < 0.75 * np.mean(rms["mode"]), rms
    assert max(rms["refined"]) < 0.02, rms


def test_hypotheses_outside_the_gate_do_not_move_it():
    """Every fifth frame the hypotheses are 1.5 m to the side (an aliased facade): the
    refined pose does not follow them."""
    truth = _drive(80)
    pf = ParticleFilter(FilterConfig(n_particles=500), MODEL, np.random.default_rng(0))
    rng = np.random.default_rng(1)
    errors = []
    for i, pose in enumerate(truth):
        offset = (0.0, 1.5) if i % 5 == 4 and i > 20 else (0.0, 0.0)
        est = pf.step(DT_S if i else 0.0, 9.0, 0.0, _hypotheses(pose, rng, offset))
        if i > 20:
            errors.append(np.linalg.norm(est.pose_world[:2] - pose[:2]))
    assert max(errors) < 0.08


def test_it_restarts_from_the_particles_when_they_move_elsewhere():
    truth = _drive(40)
    _, pf = _run(FilterConfig(n_particles=300), truth, 9.0)
    scale_before = pf.refiner.speed_scale
    restarts = pf.refiner.n_restarts
    # kidnapped: the particles are put 30 m away; the next step reports their mode
    far = truth[-1] + [0.0, 30.0, 0.0]
    pf.initialise(far, 0.1, 0.01)
    assert not pf.refiner.active
    est = pf.step(DT_S, 9.0, 0.0, Hypotheses.empty())
    assert pf.refiner.active and pf.refiner.n_restarts == restarts + 1
    np.testing.assert_allclose(est.pose_world, est.mode_world)
    assert np.linalg.norm(est.pose_world[:2] - far[:2]) < 2.0
    assert pf.refiner.speed_scale == scale_before  # the vehicle's, not the place's


def _refiner_started_off(config: FilterConfig, offset_m: float, frames: int = 5):
    """A filter tracking a straight drive whose refinement is then put ``offset_m`` to the
    side with a tight covariance (as when it starts from a mode on a wrong hypothesis,
    within the restart tolerance); the refined errors (m) of the ``frames`` frames after."""
    truth = _drive(30 + frames)
    pf = ParticleFilter(config, MODEL, np.random.default_rng(0))
    rng = np.random.default_rng(7)
    for i, pose in enumerate(truth[:30]):
        pf.step(DT_S if i else 0.0, 9.0, 0.0, _hypotheses(pose, rng))
    left = np.array([-math.sin(truth[29, 2]), math.cos(truth[29, 2])])
    pf.refiner.state[:2] += offset_m * left
    pf.refiner.covariance[:3, :3] = np.diag([0.02**2, 0.02**2, 0.002**2])
    errors = []
    for pose in truth[30:]:
        est = pf.step(DT_S, 9.0, 0.0, _hypotheses(pose, rng))
        errors.append(float(np.linalg.norm(est.pose_world[:2] - pose[:2])))
    return errors


def test_it_restarts_when_it_disagrees_with_the_particles_beyond_both_spreads():
    """0.35 m off with a 2 cm spread, within the 0.5 m tolerance, the refinement gates out
    every right hypothesis; the Mahalanobis test against the particles' mode and spread
    restarts it: at once with ``restart_after_frames=1``, after that many frames in a row
    by default."""
    config = FilterConfig(n_particles=500)
    at_once = replace(config, refine=RefineConfig(restart_after_frames=1))
    assert _refiner_started_off(at_once, 0.35)[0] < 0.08
    patience = config.refine.restart_after_frames
    errors = _refiner_started_off(config, 0.35, frames=patience + 5)
    assert min(errors[: patience - 1]) > 0.2, errors  # still its own
    assert max(errors[patience:]) < 0.08, errors  # restarted on the particles
    # on the tolerance alone it comes back only once its own spread has grown, later
    tolerance_only = replace(config, refine=RefineConfig(restart_mahalanobis_sq=None))
    assert min(_refiner_started_off(tolerance_only, 0.35, frames=patience + 5)[:patience]) > 0.2


def _pulled_stretch(config: FilterConfig, seed: int) -> tuple[float, float]:
    """A straight drive with good hypotheses, then six frames whose every hypothesis agrees
    on a pose 0.3 m ahead along the road (a moved parked car pulling every entry), then
    good again: the largest reported error (m) during and after the pulled frames."""
    truth = _drive(60)
    pf = ParticleFilter(config, MODEL, np.random.default_rng(seed))
    rng = np.random.default_rng(50 + seed)
    pulled = range(30, 36)
    errors = []
    for i, pose in enumerate(truth):
        ahead = 0.3 * np.array([math.cos(pose[2]), math.sin(pose[2])]) if i in pulled else 0.0
        est = pf.step(DT_S if i else 0.0, 9.0, 0.0, _hypotheses(pose, rng, offset_m=ahead))
        errors.append(float(np.linalg.norm(est.pose_world[:2] - pose[:2])))
    return max(errors[30:36]), max(errors[36:])


def test_a_few_frames_pulled_the_same_way_do_not_take_the_reported_pose():
    """The particles follow six frames whose hypotheses all agree 0.3 m ahead; the
    refinement, within the restart tolerance, waits ``restart_after_frames`` before
    following them and keeps the pose the motion and the earlier frames give. Restarting
    at once takes the reported pose with the particles, and there it stays after them."""
    config = FilterConfig(n_particles=500)
    at_once = replace(config, refine=RefineConfig(restart_after_frames=1))
    for seed in range(3):
        during, after = _pulled_stretch(config, seed)
        assert during < 0.12 and after < 0.12, (seed, during, after)
    assert min(min(_pulled_stretch(at_once, seed)) for seed in range(3)) > 0.2


def test_the_joint_pose_is_used_first_and_alone():
    refiner = ModeRefiner(RefineConfig())
    refiner.start(np.zeros(3), np.diag([0.1**2, 0.1**2, 0.01**2]))
    poses = np.array([[0.05, 0.0, 0.0], [-0.05, 0.0, 0.0], [0.0, 0.05, 0.0]])
    hyps = Hypotheses(
        poses,
        poses.copy(),
        np.ones(3),
        n_inliers=np.array([50, 400, 100]),
        reprojection_error_px=np.ones(3),
        joint=np.array([False, False, True]),
    )
    assert refiner.correct(hyps, MODEL) == 1
    assert refiner.pose_world[1] > 0.02 and abs(refiner.pose_world[0]) < 0.01


def test_each_model_gives_its_own_hypothesis_gaussians():
    pose_cov = np.stack([np.diag([1e-4, 4e-4, 1e-6]), np.full((3, 3), np.nan)])
    hyps = Hypotheses(
        np.zeros((2, 3)),
        np.zeros((2, 3)),
        np.ones(2),
        n_inliers=np.array([100, 25]),
        reprojection_error_px=np.array([1.0, 2.0]),
        joint=np.array([False, False]),
        pose_covariance=pose_cov,
    )
    pnp = PnpCovarianceModel(
        mu1=np.array([0.01, 0.0, 0.0]), pixel_std_px=2.0, floor=np.diag([1e-6, 1e-6, 1e-8])
    )
    model = replace(MODEL, covariance="pnp", pnp=pnp)
    centres, covs = model.hypothesis_gaussians(hyps)
    np.testing.assert_allclose(covs[0], 4.0 * pose_cov[0] + pnp.floor)
    np.testing.assert_allclose(centres[0], pnp.mu1)
    np.testing.assert_allclose(covs[1], MODEL.Sigma1)  # no C_i: the paper's
    np.testing.assert_allclose(centres[1], MODEL.mu1)
    _, paper = MODEL.hypothesis_gaussians(hyps)
    np.testing.assert_allclose(paper, np.broadcast_to(MODEL.Sigma1, (2, 3, 3)))


def test_bad_settings_are_refused():
    with pytest.raises(InvalidInputError):
        RefineConfig(speed_noise_mps=0.0)
    with pytest.raises(InvalidInputError):
        RefineConfig(speed_scale_bounds=(1.05, 1.2))
    with pytest.raises(InvalidInputError):
        _ = ModeRefiner(RefineConfig()).pose_world


def _cross_track_m(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(n,) signed error to the left of the true heading (a left turn's inside)."""
    d = est[:, :2] - truth[:, :2]
    return -np.sin(truth[:, 2]) * d[:, 0] + np.cos(truth[:, 2]) * d[:, 1]


@pytest.mark.parametrize("yaw_rate_radps", [0.47, 1.5])
def test_in_a_steady_turn_the_filter_adds_no_sideways_bias_to_its_hypotheses(yaw_rate_radps):
    """A long turn at 9 m/s (0.47 rad/s: a car-like corner held for 1.5 turns; 1.5 rad/s:
    a tight one) with unbiased hypotheses (3 cm of noise) and exact signals: over filter
    seeds 0-2 the mean cross-track error of the reported pose, and of the particles' mode
    (``refine=None``, docs/method.md's estimate), is within 3 mm of the hypotheses' own.
    A motion model that misses the arc to the outside by V dt * gamma dt / 2 every step,
    as the paper's Euler step does (here a lever arm of -V dt / 2 the truth does not
    have), puts the particles' mode more than a centimetre outside: the check can fail."""
    n = 200
    truth = _drive(n, yaw_rate_radps=yaw_rate_radps)
    late = slice(30, None)

    def mean_cross(config: FilterConfig) -> tuple[float, float]:
        filt, hyps = [], []
        for seed in range(3):
            pf = ParticleFilter(config, MODEL, np.random.default_rng(seed))
            hyp_rng = np.random.default_rng(100 + seed)
            est = np.full((n, 3), np.nan)
            joint = np.full((n, 3), np.nan)
            for i, pose in enumerate(truth):
                h = _hypotheses(pose, hyp_rng)
                joint[i] = h.pose_world[0]
                out = pf.step(DT_S if i else 0.0, 9.0, yaw_rate_radps, h)
                if out is not None:
                    est[i] = out.pose_world
            filt.append(np.mean(_cross_track_m(est[late], truth[late])))
            hyps.append(np.mean(_cross_track_m(joint[late], truth[late])))
        return float(np.mean(filt)), float(np.mean(hyps))

    config = FilterConfig(n_particles=500)
    for estimator in (config, replace(config, refine=None)):
        cross, hypotheses = mean_cross(estimator)
        assert abs(cross) <= abs(hypotheses) + 0.003, (estimator.refine, cross, hypotheses)
    mode = replace(config, refine=None)
    missing_outside = replace(mode, motion=replace(mode.motion, lever_arm_m=-9.0 * DT_S / 2))
    outward, _ = mean_cross(missing_outside)
    assert outward < -0.01, outward

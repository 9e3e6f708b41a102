"""The quality-aware measurement model: maximum-likelihood fit, likelihood, stored form."""

import json
import math

import numpy as np
import pytest

from monoloc.core.calibration import fit_quality_model
from monoloc.core.errors import InvalidInputError
from monoloc.core.measurement import (
    Hypotheses,
    MeasurementModel,
    QualityModel,
    log_likelihood,
    quality_features,
)


def _samples(rng, n, mu, Sigma, beta):
    n_inliers = rng.integers(15, 800, n)
    error_px = rng.uniform(0.3, 2.5, n)
    joint = rng.random(n) < 0.25
    log_scale = quality_features(n_inliers, error_px, joint, 100.0, 1.0) @ beta
    errors = mu + rng.multivariate_normal(np.zeros(3), Sigma, n) * np.exp(0.5 * log_scale)[:, None]
    return errors, n_inliers, error_px, joint


@pytest.mark.parametrize("seed", range(3))
def test_fit_recovers_known_parameters(seed):
    rng = np.random.default_rng(seed)
    mu = np.array([0.03, -0.02, math.radians(0.1)])
    Sigma = np.array([[0.04**2, 0.0004, 0.0], [0.0004, 0.06**2, 0.0], [0.0, 0.0, 0.004**2]])
    beta = np.array([-0.8, 1.3, -1.1])
    q = fit_quality_model(*_samples(rng, 6000, mu, Sigma, beta))
    assert np.allclose(q.beta, beta, atol=0.12)
    assert np.allclose(q.mu1[:2], mu[:2], atol=0.004)
    # The fit adds the paper fit's diagonal floor (1 cm, 1 mrad) to Sigma1.
    floor = np.diag([0.01**2, 0.01**2, 1e-3**2])
    assert np.allclose(np.sqrt(np.diag(q.Sigma1 - floor)), np.sqrt(np.diag(Sigma)), rtol=0.08)


def test_a_constant_feature_keeps_a_zero_slope():
    rng = np.random.default_rng(4)
    errors, n_inliers, error_px, _ = _samples(
        rng, 2000, np.zeros(3), np.diag([0.01, 0.01, 1e-5]), np.array([-1.0, 0.0, 0.0])
    )
    q = fit_quality_model(errors, n_inliers, error_px, np.zeros(len(errors), dtype=bool))
    assert q.beta[2] == 0.0 and q.beta[0] == pytest.approx(-1.0, abs=0.12)


def test_fit_rejects_bad_samples():
    with pytest.raises(InvalidInputError):
        fit_quality_model(np.zeros((5, 3)), np.ones(5), np.ones(5), np.zeros(5, bool))
    errors = np.zeros((20, 3))
    errors[3, 0] = np.nan
    with pytest.raises(InvalidInputError):
        fit_quality_model(errors, np.ones(20), np.ones(20), np.zeros(20, bool))


def _hypotheses(joint_pose, n_inliers, error_px):
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], joint_pose])
    return Hypotheses(
        poses,
        poses.copy(),
        np.full(3, 0.9),
        n_inliers=np.array(n_inliers, dtype=float),
        reprojection_error_px=np.array(error_px, dtype=float),
        joint=np.array([False, False, True]),
    )


def test_paper_model_ignores_joint_hypotheses_and_quality_model_weighs_by_quality():
    quality = QualityModel(Sigma1=np.diag([0.2**2, 0.2**2, 0.02**2]), beta=[-1.0, 1.0, -1.0])
    paper = MeasurementModel(quality=quality)
    particles = np.array([[2.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    hyps = _hypotheses([2.0, 0.0, 0.0], [50, 400, 800], [1.0, 1.0, 0.8])
    # The paper's model: the joint hypothesis at x = 2 is not there.
    without = Hypotheses(hyps.pose_world[:2], hyps.entry_pose_world[:2], hyps.e_vlad[:2])
    assert np.allclose(
        log_likelihood(particles, hyps, paper), log_likelihood(particles, without, paper)
    )
    # The quality model: the joint pose (most inliers) is the tightest component; the
    # many-inlier entry at x = 1 beats the 50-inlier one at x = 0.
    ll = log_likelihood(particles, hyps, paper.with_covariance("quality"))
    assert ll[0] > ll[2] > ll[1]
    # A server without quality features: the quality model falls back to the paper's.
    assert np.allclose(
        log_likelihood(particles, without, paper.with_covariance("quality")),
        log_likelihood(particles, without, paper),
    )


def test_larger_reprojection_error_widens_the_component():
    quality = QualityModel(Sigma1=np.diag([0.1**2, 0.1**2, 0.01**2]), beta=[0.0, 2.0, 0.0])
    model = MeasurementModel(quality=quality, covariance="quality")
    particle = np.array([[0.3, 0.0, 0.0]])  # 3 sigma from a 1 px hypothesis
    sharp = _hypotheses([9.0, 9.0, 0.0], [200, 200, 200], [1.0, 1.0, 1.0])
    blurred = _hypotheses([9.0, 9.0, 0.0], [200, 200, 200], [3.0, 3.0, 3.0])
    assert log_likelihood(particle, blurred, model)[0] > log_likelihood(particle, sharp, model)[0]


def test_stored_form_round_trips_and_old_calibrations_still_load():
    quality = QualityModel(mu1=[0.01, 0.0, 0.001], beta=[-0.9, 1.1, -0.5], n_ref=150.0)
    model = MeasurementModel(quality=quality, covariance="quality", source="calibrated")
    back = MeasurementModel.from_dict(json.loads(json.dumps(model.to_dict())))
    assert back.covariance == "quality"
    assert np.allclose(back.quality.beta, quality.beta) and back.quality.n_ref == 150.0
    assert np.allclose(back.quality.Sigma1, quality.Sigma1)
    # A calibration stored before the quality model: the paper's model, as before.
    old = {
        "mu1": [0.02, -0.01, 0.001],
        "Sigma1": [[0.04, 0, 0], [0, 0.04, 0], [0, 0, 0.0007]],
        "mu2": [0.9, 0.0, 0.0, 0.0],
        "Sigma2": [[0.06, 0, 0, 0], [0, 64, 0, 0], [0, 0, 64, 0], [0, 0, 0, 0.27]],
        "outlier_log_density": -16.0,
        "provenance": {"training_run": "kitti-05"},
        "updated_at": "2024-05-01T12:00:00+00:00",
    }
    loaded = MeasurementModel.from_dict(old)
    assert loaded.quality is None and loaded.covariance == "paper"
    assert np.allclose(loaded.Sigma1, old["Sigma1"])
    with pytest.raises(InvalidInputError):
        loaded.with_covariance("quality")
    with pytest.raises(InvalidInputError):
        MeasurementModel.from_dict({**old, "quality": {"mu1": [0, 0, 0]}})


def test_hypotheses_check_the_quality_features_shape():
    with pytest.raises(InvalidInputError):
        Hypotheses(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros(2), n_inliers=np.ones(3))
    assert not Hypotheses(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros(2)).has_quality


def _tailed_samples(rng, n, Sigma, beta, weight, scale):
    errors, n_inliers, error_px, joint = _samples(rng, n, np.zeros(3), Sigma, beta)
    in_tail = rng.random(n) < weight
    errors[in_tail] *= scale
    return errors, n_inliers, error_px, joint


@pytest.mark.parametrize("seed", range(2))
def test_heavy_tail_fit_recovers_the_tail_and_the_core(seed):
    rng = np.random.default_rng(10 + seed)
    # (a core well above the fit's 1 cm / 1 mrad floor, which would bias the slopes)
    Sigma = np.diag([0.06**2, 0.05**2, 0.004**2])
    beta = np.array([-0.8, 1.0, -1.0])
    samples = _tailed_samples(rng, 8000, Sigma, beta, weight=0.15, scale=5.0)
    q = fit_quality_model(*samples)
    assert q.tail_weight == pytest.approx(0.15, abs=0.03)
    assert q.tail_scale == pytest.approx(5.0, rel=0.1)
    assert np.allclose(q.beta, beta, atol=0.1)
    floor = np.diag([0.01**2, 0.01**2, 1e-3**2])
    assert np.allclose(np.sqrt(np.diag(q.Sigma1 - floor)), np.sqrt(np.diag(Sigma)), rtol=0.1)
    # One Gaussian fitted to the same samples is several times wider than the core.
    gauss = fit_quality_model(*samples, heavy_tail=False)
    assert gauss.tail_weight == 0.0
    assert np.sqrt(gauss.Sigma1[0, 0]) > 1.5 * np.sqrt(q.Sigma1[0, 0])


def test_tailed_density_is_the_two_gaussian_mixture():
    q = QualityModel(Sigma1=np.diag([0.03**2, 0.02**2, 0.001**2]), tail_weight=0.2, tail_scale=4.0)
    rng = np.random.default_rng(3)
    residuals = rng.normal(size=(5, 3)) * [0.1, 0.1, 0.003]
    log_scale = np.array([0.5])
    maha = np.einsum("ij,jk,ik->i", residuals, np.linalg.inv(q.Sigma1), residuals)[:, None]

    def gauss(cov, r):
        return np.exp(-0.5 * r @ np.linalg.inv(cov) @ r) / np.sqrt(np.linalg.det(2 * np.pi * cov))

    cov = math.exp(0.5) * q.Sigma1
    expected = [np.log(0.8 * gauss(cov, r) + 0.2 * gauss(16.0 * cov, r)) for r in residuals]
    assert np.allclose(q.component_log_density(maha, log_scale)[:, 0], expected)
    assert q.spread() == pytest.approx(0.8 + 0.2 * 16.0)


def test_a_lone_far_hypothesis_pulls_the_particles_less_with_the_tail():
    rng = np.random.default_rng(5)
    particles = rng.normal(size=(4000, 3)) * [0.05, 0.05, 0.001]
    core = np.diag([0.03**2, 0.03**2, 0.001**2])
    tailed = QualityModel(Sigma1=core, beta=[0.0, 0.0, 0.0], tail_weight=0.15, tail_scale=5.0)
    # the single Gaussian with the same covariance as the tailed mixture
    gauss = QualityModel(Sigma1=tailed.spread() * core, beta=[0.0, 0.0, 0.0])
    lone = Hypotheses(
        np.array([[0.4, 0.0, 0.0]]),
        np.array([[0.4, 0.0, 0.0]]),
        np.array([0.9]),
        n_inliers=np.array([100.0]),
        reprojection_error_px=np.array([1.0]),
        joint=np.array([False]),
    )
    shifts = []
    for quality in (gauss, tailed):
        model = MeasurementModel(quality=quality, covariance="quality", outlier_log_density=None)
        ll = log_likelihood(particles, lone, model)
        w = np.exp(ll - ll.max())
        shifts.append(float(w @ particles[:, 0] / w.sum()))
    # 0.4 m is 2.7 sigma of the Gaussian but 13 sigma of the core: the tailed model
    # treats it as a likely outlier and moves the cloud much less
    assert shifts[1] < 0.6 * shifts[0]
    assert shifts[0] > 0.05


def test_the_tail_round_trips_and_an_untailed_quality_model_still_loads():
    quality = QualityModel(beta=[-0.9, 1.1, -0.5], tail_weight=0.12, tail_scale=4.5)
    model = MeasurementModel(quality=quality, covariance="quality")
    back = MeasurementModel.from_dict(json.loads(json.dumps(model.to_dict())))
    assert back.quality.tail_weight == 0.12 and back.quality.tail_scale == 4.5
    stored = quality.to_dict()
    del stored["tail_weight"], stored["tail_scale"]
    assert QualityModel.from_dict(stored).tail_weight == 0.0
    with pytest.raises(InvalidInputError):
        QualityModel(tail_weight=1.0)
    with pytest.raises(InvalidInputError):
        QualityModel(tail_weight=0.1, tail_scale=0.5)

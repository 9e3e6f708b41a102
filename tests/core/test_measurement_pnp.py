"""The PnP-covariance measurement model (MeasurementModel covariance "pnp"): each
hypothesis weighs the particles with its own covariance, pixel_std^2 C_i + floor, from
its PnP geometry, mixed with the paper covariance's density for outliers; hypotheses
without a covariance follow the paper's density; an old server's answers (no
covariances) are weighed as the paper's model weighs them."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.special import logsumexp
from scipy.stats import multivariate_normal

from monoloc.core.errors import InvalidInputError
from monoloc.core.measurement import (
    Hypotheses,
    MeasurementModel,
    PnpCovarianceModel,
    log_likelihood,
    log_likelihood_and_distance,
)

SIGMA1 = np.diag([0.08**2, 0.06**2, math.radians(0.2) ** 2])
SIGMA2 = np.diag([0.3**2, 6.0**2, 6.0**2, math.radians(20.0) ** 2])
PNP = PnpCovarianceModel(
    mu1=np.array([0.01, -0.005, 0.0]),
    pixel_std_px=1.5,
    floor=np.diag([0.01**2, 0.01**2, math.radians(0.05) ** 2]),
)


def _model(**fields) -> MeasurementModel:
    # world axes: the hand-computed densities below are written in them
    values = dict(
        Sigma1=SIGMA1,
        Sigma2=SIGMA2,
        outlier_log_density=None,
        pnp=PNP,
        covariance="pnp",
        retrieval_frame="world",
    )
    values.update(fields)
    return MeasurementModel(**values)


def _covariance(along_m: float, across_m: float, yaw_rad: float, heading_rad: float):
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    R = np.array([[c, -s], [s, c]])
    C = np.zeros((3, 3))
    C[:2, :2] = R @ np.diag([along_m**2, across_m**2]) @ R.T
    C[2, 2] = yaw_rad**2
    return C


def _hypotheses(poses, covariances, joint=None) -> Hypotheses:
    poses = np.asarray(poses, dtype=np.float64)
    entries = poses + np.array([3.0, 1.0, 0.02])
    return Hypotheses(
        poses,
        entries,
        np.full(len(poses), 0.8),
        n_inliers=np.full(len(poses), 50.0),
        reprojection_error_px=np.full(len(poses), 1.0),
        joint=joint,
        pose_covariance=None if covariances is None else np.asarray(covariances),
    )


def _expected(particles, hyps, model, S):
    """The mixture written out with scipy: sum over hypotheses of the pose term times
    N(retrieval vector; mu2, Sigma2); the pose term (1 - w) N(residual; S_i) + w paper,
    paper = N(x - z_i - mu1_paper; Sigma1) (no paper tail here), or paper alone where
    S_i is None."""
    w = model.pnp.outlier_weight
    out = []
    for x in particles:
        terms = []
        for i in range(len(hyps)):
            paper_r = x - (hyps.pose_world[i] + model.mu1)
            paper = multivariate_normal(np.zeros(3), model.Sigma1).logpdf(paper_r)
            if S[i] is None:
                pose = paper
            else:
                r1 = x - (hyps.pose_world[i] + model.pnp.mu1)
                own = multivariate_normal(np.zeros(3), S[i]).logpdf(r1)
                pose = own if w == 0 else np.logaddexp(np.log1p(-w) + own, np.log(w) + paper)
            e = hyps.entry_pose_world[i]
            r2 = np.array([hyps.e_vlad[i], e[0] - x[0], e[1] - x[1], e[2] - x[2]]) - model.mu2
            terms.append(pose + multivariate_normal(np.zeros(4), model.Sigma2).logpdf(r2))
        out.append(logsumexp(terms))
    return np.array(out)


def test_each_hypothesis_weighs_with_its_own_covariance():
    rng = np.random.default_rng(0)
    poses = [[10.0, 5.0, 0.3], [10.2, 5.1, 0.31]]
    C = [_covariance(0.02, 0.01, 0.001, 0.3), _covariance(0.3, 0.05, 0.004, 0.3)]
    hyps = _hypotheses(poses, C)
    particles = np.array(poses[0]) + rng.normal(size=(20, 3)) * [0.2, 0.2, 0.01]
    S = [PNP.pixel_std_px**2 * c + PNP.floor for c in C]
    np.testing.assert_allclose(
        log_likelihood(particles, hyps, _model()), _expected(particles, hyps, _model(), S)
    )


def test_a_hypothesis_without_covariance_falls_back_to_sigma1_and_joint_ones_are_left_out():
    rng = np.random.default_rng(1)
    poses = [[0.0, 0.0, 0.0], [0.1, 0.05, 0.01], [0.05, 0.0, 0.0]]
    C = np.stack([_covariance(0.02, 0.01, 0.001, 0.0), np.full((3, 3), np.nan), np.eye(3)])
    hyps = _hypotheses(poses, C, joint=np.array([False, False, True]))
    particles = rng.normal(size=(15, 3)) * [0.1, 0.1, 0.01]
    per_entry = _hypotheses(poses[:2], C[:2])
    S = [PNP.pixel_std_px**2 * C[0] + PNP.floor, None]
    np.testing.assert_allclose(
        log_likelihood(particles, hyps, _model()), _expected(particles, per_entry, _model(), S)
    )


def test_outliers_follow_the_paper_density():
    """With an outlier weight w, each hypothesis's pose term is (1 - w) N(S_i) + w times
    the paper covariance's density: a precise-looking hypothesis far from a particle
    still gives it the paper model's share instead of nothing."""
    from dataclasses import replace

    rng = np.random.default_rng(7)
    model = _model(pnp=replace(PNP, outlier_weight=0.3), mu1=np.array([0.0, 0.01, 0.0]))
    poses = [[5.0, 1.0, 0.0], [5.3, 1.0, 0.0]]
    C = [_covariance(0.004, 0.003, 3e-4, 0.0), _covariance(0.01, 0.01, 5e-4, 0.0)]
    hyps = _hypotheses(poses, C)
    particles = np.array(poses[0]) + rng.normal(size=(12, 3)) * [0.2, 0.1, 0.01]
    S = [PNP.pixel_std_px**2 * c + PNP.floor for c in C]
    np.testing.assert_allclose(
        log_likelihood(particles, hyps, model), _expected(particles, hyps, model, S)
    )
    # 0.3 m from a 4 mm hypothesis: without outliers the particle is all but excluded
    far = np.array([[5.0, 1.3, 0.0]])
    alone = _hypotheses(poses[:1], C[:1])
    assert log_likelihood(far, alone, model) - log_likelihood(far, alone, _model()) > 50.0


def test_answers_without_covariances_are_weighed_as_the_paper_model_does():
    rng = np.random.default_rng(2)
    hyps = _hypotheses([[1.0, 2.0, 0.5], [1.1, 2.0, 0.5]], None)
    particles = np.array([1.0, 2.0, 0.5]) + rng.normal(size=(10, 3)) * [0.1, 0.1, 0.01]
    np.testing.assert_allclose(
        log_likelihood(particles, hyps, _model()),
        log_likelihood(particles, hyps, _model(covariance="paper")),
    )


def test_a_precise_hypothesis_outweighs_a_loose_one_that_disagrees():
    """Two hypotheses 0.4 m apart: one from inliers spread over the scene (5 mm), one
    from a cluster on one object (0.3 m across). Under the paper model they weigh alike;
    under this one the particles at the precise one win by far."""
    precise, loose = [0.0, 0.0, 0.0], [0.0, 0.4, 0.0]
    C = [_covariance(0.005, 0.005, 0.0005, 0.0), _covariance(0.3, 0.3, 0.003, 0.0)]
    hyps = _hypotheses([precise, loose], C)
    at = np.array([precise, loose])
    pnp_ll = log_likelihood(at, hyps, _model())
    paper_ll = log_likelihood(at, hyps, _model(covariance="paper"))
    assert pnp_ll[0] - pnp_ll[1] > 5.0
    assert abs(paper_ll[0] - paper_ll[1]) < 0.5


def test_the_lost_signal_uses_each_hypothesis_covariance():
    C = [_covariance(0.01, 0.01, 0.001, 0.0)]
    hyps = _hypotheses([[0.0, 0.0, 0.0]], C)
    _, closest = log_likelihood_and_distance(np.array([[0.05, 0.0, 0.0]]), hyps, _model())
    S = PNP.pixel_std_px**2 * C[0] + PNP.floor
    r = np.array([0.05, 0.0, 0.0]) - PNP.mu1
    assert closest == pytest.approx(r @ np.linalg.solve(S, r))


def test_with_the_paper_component_a_heading_half_a_degree_off_is_not_lost():
    """With the paper's density in the mixture (outlier_weight > 0) the lost signal is the
    smaller of the two components' distances: a particle on a hypothesis's position with
    its heading 0.5 deg off is far under the hypothesis's own sharp heading covariance
    (lost, beyond 25) but within the paper's Sigma1; without the paper component it is
    lost as before."""
    C = [_covariance(0.01, 0.01, 0.0005, 0.0)]
    hyps = _hypotheses([[0.0, 0.0, 0.0]], C)
    particle = np.array([[PNP.mu1[0], PNP.mu1[1], math.radians(0.5)]])
    mixed = dataclasses.replace(PNP, outlier_weight=0.3)
    _, closest = log_likelihood_and_distance(particle, hyps, _model(pnp=mixed))
    _, own_only = log_likelihood_and_distance(particle, hyps, _model())
    assert own_only > 25.0
    r = particle[0] - _model().mu1
    assert closest == pytest.approx(r @ np.linalg.solve(SIGMA1, r))
    assert closest < 25.0


def test_round_trip_and_older_calibrations():
    model = _model()
    again = MeasurementModel.from_dict(model.to_dict())
    assert again.covariance == "pnp"
    np.testing.assert_allclose(again.pnp.floor, PNP.floor)
    assert again.pnp.pixel_std_px == PNP.pixel_std_px
    old = model.to_dict()
    del old["pnp"]
    old["covariance"] = "paper"
    assert MeasurementModel.from_dict(old).pnp is None


def test_invalid_models_are_refused():
    with pytest.raises(InvalidInputError):
        MeasurementModel(covariance="pnp")
    with pytest.raises(InvalidInputError):
        PnpCovarianceModel(pixel_std_px=0.0)
    with pytest.raises(InvalidInputError):
        PnpCovarianceModel(floor=np.diag([1.0, -1.0, 1.0]))
    with pytest.raises(InvalidInputError):
        _hypotheses([[0.0, 0.0, 0.0]], np.zeros((2, 3, 3)))


def _synthetic_samples(rng, n, sigma_px, floor, mu1, outliers=None, outlier_weight=0.0):
    """Errors drawn from the model itself, with covariances C_i of varied size, shape and
    orientation (as hypotheses from near and far, spread and clustered inliers give); a
    share ``outlier_weight`` drawn from N(mu1, Sigma1) of ``outliers`` instead."""
    C = np.stack(
        [
            _covariance(
                rng.uniform(0.005, 0.2), rng.uniform(0.003, 0.05), rng.uniform(5e-4, 5e-3),
                rng.uniform(-math.pi, math.pi),
            )
            for _ in range(n)
        ]
    )  # fmt: skip
    S = sigma_px**2 * C + floor
    e = mu1 + np.einsum("nij,nj->ni", np.linalg.cholesky(S), rng.normal(size=(n, 3)))
    if outliers is not None:
        out = rng.random(n) < outlier_weight
        e[out] = rng.multivariate_normal(outliers.mu1, outliers.Sigma1, out.sum())
    return e, C


OUTLIERS = MeasurementModel(mu1=np.zeros(3), Sigma1=np.diag([0.3**2, 0.2**2, 0.01**2]))


@pytest.mark.parametrize("outliers, weight", [(None, 0.0), (OUTLIERS, 0.3)])
def test_the_fit_recovers_the_pixel_noise_and_the_floor(outliers, weight):
    from monoloc.core.calibration import fit_pnp_covariance_model

    rng = np.random.default_rng(5)
    floor = np.diag([0.02**2, 0.015**2, 0.0015**2])
    mu1 = np.array([0.01, -0.02, 0.001])
    e, C = _synthetic_samples(rng, 3000, 1.7, floor, mu1, outliers, weight)
    C[:5] = np.nan  # hypotheses without a covariance are left out
    fitted = fit_pnp_covariance_model(e, C, outliers, weight)
    assert fitted.pixel_std_px == pytest.approx(1.7, rel=0.08)
    np.testing.assert_allclose(np.sqrt(np.diag(fitted.floor)), np.sqrt(np.diag(floor)), rtol=0.15)
    np.testing.assert_allclose(fitted.mu1, mu1, atol=0.004)
    assert fitted.outlier_weight == weight
    if outliers is not None:
        # a Gaussian-only fit of the same samples is dragged wide by the outliers
        plain = fit_pnp_covariance_model(e, C, None, 0.0)
        assert np.all(np.diag(plain.floor)[:2] > 9.0 * np.diag(fitted.floor)[:2])


def test_the_fit_refuses_too_few_or_malformed_samples():
    from monoloc.core.calibration import fit_pnp_covariance_model

    rng = np.random.default_rng(6)
    e, C = _synthetic_samples(rng, 12, 1.0, np.diag([1e-4, 1e-4, 1e-6]), np.zeros(3))
    C[:5] = np.nan
    with pytest.raises(InvalidInputError, match="at least 10"):
        fit_pnp_covariance_model(e, C)
    with pytest.raises(InvalidInputError):
        fit_pnp_covariance_model(e, C[:, :2])
    with pytest.raises(InvalidInputError):
        fit_pnp_covariance_model(e, C, OUTLIERS, 1.0)

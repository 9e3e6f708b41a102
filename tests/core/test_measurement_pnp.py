"""The PnP-covariance measurement model (MeasurementModel covariance "pnp"): each
hypothesis weighs the particles with its own covariance, pixel_std^2 C_i + floor, from
its PnP geometry; hypotheses without one fall back to Sigma1; an old server's answers
(no covariances) are weighed as the paper's model weighs them."""

from __future__ import annotations

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
    values = dict(Sigma1=SIGMA1, Sigma2=SIGMA2, outlier_log_density=None, pnp=PNP, covariance="pnp")
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
    """The mixture written out with scipy: sum over hypotheses of N(pose residual; S_i)
    times N(retrieval vector; mu2, Sigma2)."""
    out = []
    for x in particles:
        terms = []
        for i in range(len(hyps)):
            r1 = x - (hyps.pose_world[i] + model.pnp.mu1)
            r1[2] = (r1[2] + math.pi) % (2 * math.pi) - math.pi
            e = hyps.entry_pose_world[i]
            r2 = np.array([hyps.e_vlad[i], e[0] - x[0], e[1] - x[1], e[2] - x[2]]) - model.mu2
            terms.append(
                multivariate_normal(np.zeros(3), S[i]).logpdf(r1)
                + multivariate_normal(np.zeros(4), model.Sigma2).logpdf(r2)
            )
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
    S = [PNP.pixel_std_px**2 * C[0] + PNP.floor, SIGMA1]
    np.testing.assert_allclose(
        log_likelihood(particles, hyps, _model()), _expected(particles, per_entry, _model(), S)
    )


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


def _synthetic_samples(rng, n, sigma_px, floor, mu1, tail_weight=0.0, tail_scale=1.0):
    """Errors drawn from the model itself, with covariances C_i of varied size, shape and
    orientation (as hypotheses from near and far, spread and clustered inliers give)."""
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
    scale = np.where(rng.random(n) < tail_weight, tail_scale, 1.0)
    e = mu1 + scale[:, None] * np.einsum(
        "nij,nj->ni", np.linalg.cholesky(S), rng.normal(size=(n, 3))
    )
    return e, C


@pytest.mark.parametrize("tail", [(0.0, 1.0), (0.3, 10.0)])
def test_the_fit_recovers_the_pixel_noise_and_the_floor(tail):
    from monoloc.core.calibration import fit_pnp_covariance_model

    rng = np.random.default_rng(5)
    floor = np.diag([0.02**2, 0.015**2, 0.0015**2])
    mu1 = np.array([0.01, -0.02, 0.001])
    e, C = _synthetic_samples(rng, 3000, 1.7, floor, mu1, *tail)
    C[:5] = np.nan  # hypotheses without a covariance are left out
    fitted = fit_pnp_covariance_model(e, C, *tail)
    assert fitted.pixel_std_px == pytest.approx(1.7, rel=0.08)
    np.testing.assert_allclose(np.sqrt(np.diag(fitted.floor)), np.sqrt(np.diag(floor)), rtol=0.15)
    np.testing.assert_allclose(fitted.mu1, mu1, atol=0.004)
    assert (fitted.tail_weight, fitted.tail_scale) == tail


def test_the_fit_refuses_too_few_or_malformed_samples():
    from monoloc.core.calibration import fit_pnp_covariance_model

    rng = np.random.default_rng(6)
    e, C = _synthetic_samples(rng, 12, 1.0, np.diag([1e-4, 1e-4, 1e-6]), np.zeros(3))
    C[:5] = np.nan
    with pytest.raises(InvalidInputError, match="at least 10"):
        fit_pnp_covariance_model(e, C)
    with pytest.raises(InvalidInputError):
        fit_pnp_covariance_model(e, C[:, :2])

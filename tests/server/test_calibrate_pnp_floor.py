"""The PnP floor fitted in the form the vehicle frame applies it (server.calibrate,
CalibrationConfig.pnp_floor_fit "isotropic_ml")."""

import math

import numpy as np
import pytest
from calibration_samples import synthetic_samples

from monoloc.core.errors import InvalidInputError
from monoloc.core.measurement import MeasurementModel, PnpCovarianceModel
from monoloc.server.calibrate import CalibrationConfig, fit_isotropic_pnp, fit_samples

OUTLIERS = MeasurementModel(
    Sigma1=np.diag([0.15**2, 0.15**2, 0.005**2]), tail_weight=0.3, tail_scale=10.0
)


def _covariances(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3, 3) PnP covariances at 1 px as a forward camera gives them: centimetres
    along, millimetres across, the across error and the heading correlated."""
    out = np.empty((n, 3, 3))
    for i in range(n):
        along, across, heading = (
            rng.uniform(0.005, 0.03),
            rng.uniform(0.002, 0.01),
            rng.uniform(2e-4, 1e-3),
        )
        rho = rng.uniform(0.5, 0.9)
        out[i] = [
            [along**2, 0.0, 0.0],
            [0.0, across**2, rho * across * heading],
            [0.0, rho * across * heading, heading**2],
        ]
    return out


def _draw(rng, C, pixel_std, floor_std, bias=np.zeros(3)) -> np.ndarray:
    """Errors (n, 3) ~ N(bias, pixel_std^2 C_i + diag(floor_std^2))."""
    S = pixel_std**2 * C + np.diag(np.square(floor_std))
    L = np.linalg.cholesky(S)
    return bias + np.einsum("nij,nj->ni", L, rng.normal(size=(len(C), 3)))


def _isotropic_nll(model: PnpCovarianceModel, e: np.ndarray, C: np.ndarray) -> float:
    """The samples' negative log-likelihood under a PnP term as the vehicle frame applies
    it: (1 - w) N(mu1, sigma^2 C + floor) + w paper, the floor as stored."""
    S = model.pixel_std_px**2 * C + model.floor
    r = e - model.mu1
    maha = np.einsum("ni,ni->n", r, np.linalg.solve(S, r[:, :, None])[:, :, 0])
    own = -0.5 * (np.linalg.slogdet(S)[1] + 3 * math.log(2 * math.pi) + maha)
    rp = e - OUTLIERS.mu1
    paper = OUTLIERS.paper_log_density(
        np.einsum("ni,ij,nj->n", rp, np.linalg.inv(OUTLIERS.Sigma1), rp)
    )
    w = model.outlier_weight
    return -float(np.logaddexp(own + math.log1p(-w), paper + math.log(w)).sum())


def _half_trace(model: PnpCovarianceModel) -> PnpCovarianceModel:
    f2 = 0.5 * (model.floor[0, 0] + model.floor[1, 1])
    return PnpCovarianceModel(
        model.mu1, model.pixel_std_px, np.diag([f2, f2, model.floor[2, 2]]), model.outlier_weight
    )


def test_an_isotropic_floor_is_recovered():
    rng = np.random.default_rng(0)
    C = _covariances(rng, 3000)
    e = _draw(rng, C, 1.4, [0.006, 0.006, 3e-4], bias=np.array([0.002, -0.001, 1e-4]))
    start = PnpCovarianceModel(np.zeros(3), 1.0, np.diag([0.02**2, 0.02**2, 1e-6]), 0.3)
    fitted = fit_isotropic_pnp(e, C, OUTLIERS, start)
    assert fitted.floor[0, 0] == fitted.floor[1, 1]
    assert math.sqrt(fitted.floor[0, 0]) == pytest.approx(0.006, rel=0.15)
    assert fitted.pixel_std_px == pytest.approx(1.4, rel=0.1)
    assert np.all(np.abs(fitted.mu1 - [0.002, -0.001, 1e-4]) < [5e-4, 5e-4, 3e-5])
    assert fitted.outlier_weight == 0.3


def test_the_fit_beats_half_the_trace_of_an_along_across_fit_on_the_model_it_is_applied_as():
    # a straight road's split: no floor along, a wide one across (what the along / across
    # fit gives when the across-heading ambiguity lands on the across axis)
    rng = np.random.default_rng(1)
    C = _covariances(rng, 400)
    e = _draw(rng, C, 1.5, [1e-4, 0.02, 1e-5])
    anisotropic = PnpCovarianceModel(np.zeros(3), 1.5, np.diag([1e-4**2, 0.02**2, 1e-5**2]), 0.3)
    half = _half_trace(anisotropic)
    fitted = fit_isotropic_pnp(e, C, OUTLIERS, anisotropic)
    assert _isotropic_nll(fitted, e, C) < _isotropic_nll(half, e, C) - 5.0
    # the half trace is one of its starts: the fit never ends worse than it
    assert math.sqrt(fitted.floor[0, 0]) != pytest.approx(math.sqrt(half.floor[0, 0]), rel=0.05)


def _straight_road_samples(seed: int, n: int = 300):
    """CalibrationSamples of a straight road along world X whose per-entry errors follow
    a PnP term with no floor along and 2 cm across."""
    rng = np.random.default_rng(seed)
    truth = np.column_stack(
        [np.linspace(0.0, 120.0, n), rng.normal(0.0, 0.05, n), rng.normal(0.0, 0.01, n)]
    )
    C = _covariances(rng, n)  # along / across the heading (about world X here)
    error = _draw(rng, C, 1.5, [1e-4, 0.02, 1e-5])
    offsets = np.column_stack([rng.normal(2.0, 6.0, n), rng.normal(0.0, 0.3, n)])
    samples = synthetic_samples(rng, truth, truth - error, offsets, C)
    return samples


def test_fit_samples_stores_the_isotropic_fit_and_the_default_is_unchanged():
    from monoloc.server.vision.vocabulary import load_default_vocabulary

    samples = _straight_road_samples(2)
    per_run = [{"query_frames": len(samples.truth), "used": len(samples.truth)}]
    vocabulary = load_default_vocabulary()
    product = fit_samples(samples, per_run, ["road"], CalibrationConfig(), vocabulary).model
    refit = fit_samples(
        samples, per_run, ["road"], CalibrationConfig(pnp_floor_fit="isotropic_ml"), vocabulary
    ).model
    assert CalibrationConfig().pnp_floor_fit == "half_trace"
    assert refit.pnp.floor[0, 0] == refit.pnp.floor[1, 1]
    assert product.pnp.floor[0, 0] == pytest.approx(product.pnp.floor[1, 1])
    # the half trace carries the 2 cm across floor onto both axes (~1.4 cm); the refit
    # is another, likelier floor, and the rest of the model is the product's
    assert math.sqrt(product.pnp.floor[0, 0]) > 0.01
    assert abs(math.sqrt(refit.pnp.floor[0, 0]) - math.sqrt(product.pnp.floor[0, 0])) > 0.002
    np.testing.assert_array_equal(refit.Sigma2, product.Sigma2)
    np.testing.assert_array_equal(refit.mu1, product.mu1)


def test_the_isotropic_fit_needs_the_vehicle_frame():
    with pytest.raises(InvalidInputError, match="vehicle"):
        CalibrationConfig(pnp_floor_fit="isotropic_ml", retrieval_frame="world")

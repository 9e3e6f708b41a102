"""bench/transfer.py's model baselines: the retrieval term made constant, the e_vlad
spread widened by the fit check (issue 47)."""

import math

import numpy as np

from bench.transfer import NO_RETRIEVAL_LOG_WEIGHT, widened, without_retrieval
from monoloc.core.measurement import Hypotheses, MeasurementModel, log_likelihood


def _pose_only_log_likelihood(particles, hypotheses, model):
    """log[sum_i exp(log N(x; z_i + mu1, Sigma1) + W) + exp(floor)], written out."""
    inv = np.linalg.inv(model.Sigma1)
    _, log_det = np.linalg.slogdet(model.Sigma1)
    r = particles[:, None, :] - (hypotheses.pose_world + model.mu1)[None, :, :]
    r[..., 2] = (r[..., 2] + math.pi) % (2 * math.pi) - math.pi
    maha = np.einsum("phi,ij,phj->ph", r, inv, r)
    terms = -0.5 * (maha + log_det + 3 * math.log(2 * math.pi)) + NO_RETRIEVAL_LOG_WEIGHT
    terms = np.concatenate([terms, np.full((len(particles), 1), model.outlier_log_density)], 1)
    return np.logaddexp.reduce(terms, axis=1)


def test_without_retrieval_weighs_hypotheses_by_their_pose_alone():
    rng = np.random.default_rng(3)
    hypotheses = Hypotheses(
        rng.normal(0.0, 1.0, (6, 3)), rng.normal(0.0, 4.0, (6, 3)), rng.uniform(1.0, 1.4, 6)
    )
    # particles around the hypotheses, where the pose term is above the outlier floor
    near = hypotheses.pose_world[rng.integers(0, 6, 400)]
    particles = near + rng.normal(0.0, 1.0, (400, 3)) * np.array([0.1, 0.1, 0.02])
    model = MeasurementModel(
        retrieval_frame="world",  # the pose term is written out in world axes above
        Sigma1=np.diag([0.05**2, 0.08**2, 1e-3]),
        mu2=np.array([1.1, 0.5, 0.0, 0.0]),
        Sigma2=np.diag([0.05**2, 1.0, 2.5**2, 0.05**2]),
    )
    expected = _pose_only_log_likelihood(particles, hypotheses, model)
    flat = log_likelihood(particles, hypotheses, without_retrieval(model))
    # the same posterior: the log-likelihoods differ by one constant over all particles
    assert np.ptp(flat - expected) < 1e-6
    # the model it came from weighs them otherwise (so the check above can fail)
    assert np.ptp(log_likelihood(particles, hypotheses, model) - expected) > 1.0


def test_widened_scales_the_vlad_spread_by_the_fit_checks_shift():
    model = MeasurementModel(Sigma2=np.diag([0.05**2, 1.0, 4.0, 0.01]))
    provenance = {"vlad_neighbours": {"mean": 1.10, "std": 0.05, "n": 40}}
    far = {"distances": list(np.random.default_rng(0).normal(1.25, 0.03, 200))}
    out = widened(model, provenance, far)
    shift = (np.mean(far["distances"]) - 1.10) / 0.05
    assert math.isclose(math.sqrt(out.Sigma2[0, 0]), 0.05 * abs(shift), rel_tol=1e-9)
    np.testing.assert_array_equal(out.Sigma2[1:, 1:], model.Sigma2[1:, 1:])
    near = {"distances": [1.09, 1.11, 1.10, 1.12]}  # within one spread: unchanged
    np.testing.assert_array_equal(widened(model, provenance, near).Sigma2, model.Sigma2)

"""A filter calibrated on one straight street keeps using its hypotheses on a cross street.

Regression of dev city 6: the training run drove one street along X, so the retrieval
term's Sigma2 was centimetres wide across it; on a street along Y every mixture component
fell under the outlier floor, the likelihood went flat and the filter dead-reckoned away
from hypotheses that were within centimetres of the truth.
"""

import dataclasses
import math

import numpy as np

from monoloc.client.particle_filter import FilterConfig, ParticleFilter
from monoloc.core.calibration import fit_measurement_model, retrieval_vectors
from monoloc.core.measurement import Hypotheses


def _model_from_one_straight_street(rng):
    n = 400
    truth = np.column_stack([rng.uniform(0, 300, n), np.zeros(n), np.zeros(n)])
    entry = truth + np.column_stack(
        [rng.uniform(-4, 4, n), rng.normal(0, 0.01, n), rng.normal(0, 1e-4, n)]
    )
    errors = rng.normal(size=(n, 3)) * [0.03, 0.03, 0.001]
    samples = retrieval_vectors(rng.normal(0.9, 0.05, n), entry, truth)
    clamped = fit_measurement_model(errors, samples)
    # what the fit gave before the minimum spread: the samples' own covariance
    raw = np.cov(samples.T) + np.diag(np.square([0.01, 0.05, 0.05, 1e-3]))
    return clamped, dataclasses.replace(clamped, Sigma2=raw)


def _drive_along_y(model, seed):
    """Final-half mean position error (m) of a filter driven 150 frames north at 9 m/s
    with a 0.003 rad/s gyro bias, each frame with six hypotheses around the truth from
    entries of a map lap driven a metre to the side."""
    rng = np.random.default_rng(seed)
    pf = ParticleFilter(FilterConfig(n_particles=500), model, rng)
    dt, speed, heading = 0.1, 9.0, math.pi / 2
    errors = []
    for frame in range(150):
        truth = np.array([0.0, speed * dt * frame, heading])
        poses = truth + rng.normal(size=(6, 3)) * [0.03, 0.03, 0.001]
        # the map lap's entries, one every 0.9 m, the query's frames half-way between
        # them, ahead and behind; the map lap a metre to the side, headings a little off
        # (a later drive is never on the map's line)
        entries = truth + np.column_stack(
            [rng.normal(1.0, 0.1, 6), 0.45 + 0.9 * np.arange(-3, 3), rng.normal(0, 0.01, 6)]
        )
        hyps = Hypotheses(poses, entries, rng.normal(0.9, 0.03, 6))
        estimate = pf.step(dt, speed, 0.003, hyps)
        if estimate is not None and frame >= 75:
            errors.append(np.hypot(*(estimate.pose_world[:2] - truth[:2])))
    return float(np.mean(errors))


def test_a_cross_street_still_pulls_the_filter_to_its_hypotheses():
    clamped, raw = _model_from_one_straight_street(np.random.default_rng(0))
    assert math.sqrt(raw.Sigma2[2, 2]) < 0.1  # the degenerate spread across the street
    assert math.sqrt(clamped.Sigma2[2, 2]) >= 1.0
    with_minimum = _drive_along_y(clamped, seed=1)
    without = _drive_along_y(raw, seed=1)
    assert with_minimum < 0.05, with_minimum
    # the old fit: flat likelihood, dead reckoning with the gyro's bias
    assert without > 5 * with_minimum, (without, with_minimum)

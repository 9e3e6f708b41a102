"""The retrieval term's VLAD evidence read against the frame's own best
(``MeasurementModel.vlad_evidence="relative"``): a street whose every VLAD distance is
larger than the training street's must not push the frame's hypotheses under the outlier
floor, as the absolute term calibrated tight on one street does."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from monoloc.core.calibration import fit_relative_vlad
from monoloc.core.errors import InvalidInputError
from monoloc.core.measurement import Hypotheses, MeasurementModel, log_likelihood

TRUTH = np.array([10.0, 5.0, 0.3])


def _frame(e_vlad_shift: float) -> Hypotheses:
    """Five hypotheses within 2 cm of the truth; entries 0-4 m ahead; VLAD distances of a
    street like the training one (1.10-1.14), shifted by ``e_vlad_shift``."""
    rng = np.random.default_rng(0)
    poses = TRUTH + rng.normal(0.0, [0.02, 0.02, 0.002], (5, 3))
    ahead = np.arange(5.0)
    entries = np.c_[
        TRUTH[0] + ahead * np.cos(TRUTH[2]), TRUTH[1] + ahead * np.sin(TRUTH[2]), np.full(5, 0.3)
    ]
    return Hypotheses(poses, entries, np.linspace(1.10, 1.14, 5) + e_vlad_shift)


def _calibrated(vlad_evidence: str) -> MeasurementModel:
    """A model calibrated on one street: e_vlad 1.097 +- 0.052, relative 0.02 +- 0.015."""
    return MeasurementModel(
        Sigma1=np.diag([0.03**2, 0.03**2, 0.003**2]),
        mu2=np.array([1.097, 2.0, 0.0, 0.0]),
        Sigma2=np.diag([0.052**2, 1.5**2, 1.5**2, 0.05**2]),
        vlad_evidence=vlad_evidence,
        relative_vlad=(0.02, 0.015),
    )


def _contrast(model: MeasurementModel, hyps: Hypotheses) -> float:
    """log p(z | truth) - log p(z | 1 m aside): what the frame tells the filter."""
    particles = np.stack([TRUTH, TRUTH + [0.0, 1.0, 0.0]])
    ll = log_likelihood(particles, hyps, model)
    return float(ll[0] - ll[1])


def test_absolute_evidence_fades_on_a_street_of_larger_vlad_distances_relative_does_not():
    absolute, relative = _calibrated("absolute"), _calibrated("relative")
    home, away = _frame(0.0), _frame(0.26)  # 5 sigma of the training street
    # on a street like the training one both read the frame alike
    assert _contrast(absolute, home) > 20 and _contrast(relative, home) > 20
    # away, the absolute term sinks every hypothesis toward the outlier floor
    assert _contrast(absolute, away) < 0.75 * _contrast(absolute, home)
    # the relative one reads the same frame as at home: the shift cancels
    assert _contrast(relative, away) == pytest.approx(_contrast(relative, home), rel=1e-9)


def test_relative_evidence_still_prefers_the_frame_s_closer_vlad_match():
    """Two hypotheses 3 m apart: the one with the frame's best VLAD distance wins."""
    model = _calibrated("relative")
    poses = np.array([TRUTH, TRUTH + [0.0, 3.0, 0.0]])
    hyps = Hypotheses(poses, poses.copy(), np.array([1.30, 1.40]))
    ll = log_likelihood(poses, hyps, model)
    assert ll[0] > ll[1] + 5.0
    swapped = dataclasses.replace(hyps, e_vlad=np.array([1.40, 1.30]))
    ll = log_likelihood(poses, swapped, model)
    assert ll[1] > ll[0] + 5.0


def test_vlad_evidence_round_trips_old_calibrations_are_absolute_and_bad_values_refused():
    model = _calibrated("relative")
    again = MeasurementModel.from_dict(model.to_dict())
    assert again.vlad_evidence == "relative" and again.relative_vlad == (0.02, 0.015)
    old = model.to_dict()
    del old["vlad_evidence"], old["relative_vlad"]
    assert MeasurementModel.from_dict(old).vlad_evidence == "absolute"
    assert model.with_vlad_evidence("absolute").vlad_evidence == "absolute"
    with pytest.raises(InvalidInputError, match="vlad_evidence"):
        dataclasses.replace(model, vlad_evidence="rank")
    with pytest.raises(InvalidInputError, match="relative_vlad"):
        dataclasses.replace(model, relative_vlad=(0.0, 0.0))


def test_fit_relative_vlad_takes_mean_and_std_with_a_floor():
    mean, std = fit_relative_vlad(np.array([0.0, 0.02, 0.04, 0.06]))
    assert mean == pytest.approx(0.03) and std == pytest.approx(
        np.std([0, 0.02, 0.04, 0.06], ddof=1)
    )
    assert fit_relative_vlad(np.zeros(10))[1] == pytest.approx(0.01)
    assert fit_relative_vlad(np.array([0.1])) == MeasurementModel().relative_vlad

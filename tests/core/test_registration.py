"""The run-registration correction: outliers, evidence and time (monoloc.core.registration)."""

from __future__ import annotations

import numpy as np
import pytest

from monoloc.core.errors import InvalidInputError
from monoloc.core.registration import RegistrationConfig, run_correction


def _measurements(rng, times_s, offset_fn, noise_m=0.01):
    return np.array([offset_fn(t) for t in times_s]) + noise_m * rng.standard_normal(
        (len(times_s), 2)
    )


def test_a_constant_offset_is_recovered_despite_wrong_places():
    rng = np.random.default_rng(0)
    times = np.arange(0.0, 20.0, 0.1)
    offsets = _measurements(rng, times, lambda t: (0.06, -0.04))
    offsets[::10] = rng.uniform(
        -0.7, 0.7, (len(offsets[::10]), 2)
    )  # aliased frames, within the gate
    correction = run_correction(times, times, offsets)
    assert correction.measured == len(times)
    assert correction.used < correction.measured  # the wrong places were dropped
    np.testing.assert_allclose(correction.offsets_m, [[0.06, -0.04]] * len(times), atol=0.005)
    assert correction.summary()["frames_used"] == correction.used


def test_no_measurement_or_too_few_leaves_the_run_where_it_was():
    times = np.arange(0.0, 20.0, 0.1)
    none = run_correction(times, np.zeros(0), np.zeros((0, 2)))
    assert none.measured == 0 and not none.offsets_m.any()
    rng = np.random.default_rng(1)
    few_times = times[:5]
    few = run_correction(times, few_times, _measurements(rng, few_times, lambda t: (0.1, 0.1)))
    assert few.used == 5 and not few.offsets_m.any()  # below min_frames: not moved
    lenient = RegistrationConfig(min_frames=5)
    moved = run_correction(
        times, few_times, _measurements(rng, few_times, lambda t: (0.1, 0.1)), lenient
    )
    assert moved.offsets_m[0, 0] > 0.05


def test_offsets_beyond_the_gate_are_not_evidence():
    times = np.arange(0.0, 10.0, 0.1)
    far = np.full((len(times), 2), 3.0)  # a run 4 m off is a wrong place, not INS drift
    correction = run_correction(times, times, far)
    assert correction.measured == 0 and not correction.offsets_m.any()


def test_a_slow_drift_is_followed_and_far_frames_fall_back_to_the_prior():
    rng = np.random.default_rng(2)
    times = np.arange(0.0, 300.0, 0.5)
    config = RegistrationConfig(time_scale_s=20.0)
    # measured only in the first 200 s, drifting from 0 to 0.2 m in x
    measured_t = times[times < 200.0]
    offsets = _measurements(rng, measured_t, lambda t: (0.001 * t, 0.0))
    correction = run_correction(times, measured_t, offsets, config)
    at = {t: correction.offsets_m[np.searchsorted(times, t)] for t in (20.0, 100.0, 180.0)}
    for t, value in at.items():
        assert value[0] == pytest.approx(0.001 * t, abs=0.02)
        assert abs(value[1]) < 0.01
    # 100 s after the last measurement (5 kernel widths) the prior holds it near zero
    assert abs(correction.offsets_m[-1, 0]) < 0.02


def test_bad_arguments_are_refused():
    with pytest.raises(InvalidInputError):
        RegistrationConfig(prior_std_m=0.0)
    with pytest.raises(InvalidInputError):
        RegistrationConfig(every=0)
    with pytest.raises(InvalidInputError):
        run_correction(np.zeros(3), np.zeros(2), np.zeros((3, 2)))
    with pytest.raises(InvalidInputError):
        run_correction(np.array([np.nan]), np.zeros(1), np.zeros((1, 2)))

"""The fitted pose-error bias kept only as far as it is significant (server.calibrate)."""

import numpy as np
import pytest

from monoloc.core.errors import InvalidInputError
from monoloc.server.calibrate import (
    bias_standard_error,
    bias_z_squared,
    shrunk_bias,
)

# per-entry pose errors as a training road gives them: along / across (m), heading (rad)
ERROR_STD = np.array([0.03, 0.03, 0.002])
N_SAMPLES = 400


def _samples(bias_in_se: float, direction: np.ndarray, seed: int) -> np.ndarray:
    """(N, 3) errors whose true mean lies ``bias_in_se`` standard errors along the unit
    ``direction`` (in units of each component's standard error)."""
    rng = np.random.default_rng(seed)
    se = ERROR_STD / np.sqrt(N_SAMPLES)
    noise = rng.normal(size=(N_SAMPLES, 3))
    noise -= noise.mean(axis=0)  # the sample mean exactly the true mean
    noise /= noise.std(axis=0, ddof=1)
    return bias_in_se * direction * se + noise * ERROR_STD


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_bias_of_10_standard_errors_is_kept_within_a_few_percent(seed):
    direction = np.array([1.0, -1.0, 0.5]) / np.linalg.norm([1.0, -1.0, 0.5])
    errors = _samples(10.0, direction, seed)
    mean = errors.mean(axis=0)
    se = bias_standard_error(errors)
    assert bias_z_squared(mean, se) == pytest.approx(100.0, rel=0.2)
    kept = shrunk_bias(mean, se, "james_stein")
    assert np.linalg.norm(kept) == pytest.approx(np.linalg.norm(mean), rel=0.03)
    np.testing.assert_array_equal(shrunk_bias(mean, se, "significance_gate"), mean)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("method", ["james_stein", "significance_gate"])
def test_a_bias_of_half_a_standard_error_is_shrunk_to_zero(seed, method):
    direction = np.ones(3) / np.sqrt(3.0)
    errors = _samples(0.5, direction, seed)
    shrunk = shrunk_bias(errors.mean(axis=0), bias_standard_error(errors), method)
    np.testing.assert_array_equal(shrunk, np.zeros(3))


def test_the_shrunk_bias_keeps_its_direction():
    # about 2 standard errors per component: shrunk, not zeroed
    direction = np.array([0.2, -0.9, 0.4]) / np.linalg.norm([0.2, -0.9, 0.4])
    errors = _samples(3.0, direction, 3)
    mean = errors.mean(axis=0)
    shrunk = shrunk_bias(mean, bias_standard_error(errors), "james_stein")
    factor = np.linalg.norm(shrunk) / np.linalg.norm(mean)
    assert 0.5 < factor < 1.0
    np.testing.assert_allclose(shrunk, factor * mean, rtol=1e-12)
    assert factor == pytest.approx(1.0 - 1.0 / 9.0, rel=0.1)


def test_the_scale_of_a_component_does_not_change_its_standing():
    # the heading in rad or mrad: the same significance, the same shrinkage factor
    errors = _samples(2.5, np.array([0.6, 0.0, 0.8]), 4)
    mean, se = errors.mean(axis=0), bias_standard_error(errors)
    scale = np.diag([1.0, 1.0, 1000.0])
    in_rad = shrunk_bias(mean, se, "james_stein")
    in_mrad = shrunk_bias(scale @ mean, scale @ se @ scale, "james_stein")
    np.testing.assert_allclose(scale @ in_rad, in_mrad, rtol=1e-9)


def test_none_keeps_the_fit_and_unknown_methods_are_refused():
    mean, se = np.array([0.01, -0.02, 0.001]), np.diag([1e-4, 1e-4, 1e-6])
    np.testing.assert_array_equal(shrunk_bias(mean, se, "none"), mean)
    with pytest.raises(InvalidInputError):
        shrunk_bias(mean, se, "median")  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError):
        shrunk_bias(mean[:2], se[:2, :2], "james_stein")

"""The fitted pose-error bias kept only as far as it is significant (server.calibrate)."""

import numpy as np
import pytest
from calibration_samples import synthetic_samples

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


def test_along_only_zeroes_the_across_component_whatever_its_significance():
    # 20 standard errors across, 0.3 along: across goes, along and heading stay as fitted
    se = np.diag((ERROR_STD / np.sqrt(N_SAMPLES)) ** 2)
    mean = np.array([0.3, 20.0, -4.0]) * np.sqrt(np.diag(se))
    kept = shrunk_bias(mean, se, "along_only")
    np.testing.assert_array_equal(kept, [mean[0], 0.0, mean[2]])
    with pytest.raises(InvalidInputError):
        shrunk_bias(mean[:2], se[:2, :2], "along_only")


def _heading_axis_samples(seed: int, n: int = 300):
    """CalibrationSamples of a road along world Y (heading +90 deg) whose per-entry pose
    errors carry a bias of 4 cm along and 6 cm across the heading, 3 mrad in heading."""
    from monoloc.core.measurement import to_heading_axes

    rng = np.random.default_rng(seed)
    heading_rad = np.pi / 2 + rng.normal(0.0, 0.05, n)
    truth = np.column_stack([rng.normal(0.0, 2.0, n), np.linspace(0.0, 150.0, n), heading_rad])
    bias_world = np.array([-0.06, 0.04])  # across (+world -X) and along (+world Y) here
    error_world = np.column_stack(
        [
            bias_world[0] + rng.normal(0.0, 0.03, n),
            bias_world[1] + rng.normal(0.0, 0.03, n),
            0.003 + rng.normal(0.0, 0.002, n),
        ]
    )
    hypothesis = truth - error_world
    covariance = np.diag([0.02**2, 0.02**2, 0.002**2])
    errors_heading, _ = to_heading_axes(
        error_world, hypothesis[:, 2], np.repeat(covariance[None], n, 0)
    )
    offsets = rng.normal(0.0, 2.0, (n, 2))
    samples = synthetic_samples(rng, truth, hypothesis, offsets, np.repeat(covariance[None], n, 0))
    return samples, errors_heading.mean(axis=0)


def test_the_along_only_fit_drops_the_across_bias_of_both_terms_and_keeps_the_rest():
    from monoloc.server.calibrate import CalibrationConfig, fit_samples
    from monoloc.server.vision.vocabulary import load_default_vocabulary

    samples, mean_heading_axes = _heading_axis_samples(0)
    # the planted bias reads along / across the heading: (0.04, 0.06, 0.003)
    assert mean_heading_axes[0] == pytest.approx(0.04, abs=0.005)
    assert mean_heading_axes[2] == pytest.approx(0.003, abs=0.0005)
    assert abs(mean_heading_axes[1]) == pytest.approx(0.06, abs=0.005)
    per_run = [{"query_frames": len(samples.truth), "used": len(samples.truth)}]
    vocabulary = load_default_vocabulary()
    fitted = fit_samples(samples, per_run, ["road"], CalibrationConfig(), vocabulary).model
    along = fit_samples(
        samples, per_run, ["road"], CalibrationConfig(bias_shrinkage="along_only"), vocabulary
    ).model
    assert abs(fitted.mu1[1]) > 0.05 and abs(fitted.pnp.mu1[1]) > 0.05
    for before, after in ((fitted.mu1, along.mu1), (fitted.pnp.mu1, along.pnp.mu1)):
        np.testing.assert_array_equal(after, before * np.array([1.0, 0.0, 1.0]))
    np.testing.assert_array_equal(along.Sigma1, fitted.Sigma1)
    with pytest.raises(InvalidInputError, match="vehicle"):
        fit_samples(
            samples,
            per_run,
            ["road"],
            CalibrationConfig(bias_shrinkage="along_only", retrieval_frame="world"),
            vocabulary,
        )

"""A condition's calibration (MeasurementModel.conditions): hypotheses whose entry carries
the condition's tag are weighed by that model's mixture terms, the others by the base
model's; answers without tags (an older server) and a model without conditions are
weighed as before; the conditions survive the stored form."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from monoloc.core.errors import InvalidInputError
from monoloc.core.measurement import (
    Hypotheses,
    MeasurementModel,
    PnpCovarianceModel,
    log_likelihood,
    log_likelihood_and_distance,
)

DAY = MeasurementModel(
    Sigma1=np.diag([0.05**2, 0.04**2, math.radians(0.2) ** 2]),
    Sigma2=np.diag([0.3**2, 6.0**2, 6.0**2, math.radians(20.0) ** 2]),
    outlier_log_density=None,
    pnp=PnpCovarianceModel(pixel_std_px=1.0, floor=np.diag([1e-4, 1e-4, 1e-7])),
    covariance="pnp",
)
# a night calibration: broader pose errors, a different VLAD distance and bias
NIGHT = dataclasses.replace(
    DAY,
    mu1=np.array([0.02, -0.01, 0.001]),
    Sigma1=np.diag([0.25**2, 0.12**2, math.radians(0.4) ** 2]),
    mu2=np.array([1.2, 0.0, 0.0, 0.0]),
    pnp=PnpCovarianceModel(pixel_std_px=2.5, floor=np.diag([4e-4, 4e-4, 1e-6])),
)


def _hypotheses(poses, tags) -> Hypotheses:
    poses = np.asarray(poses, dtype=np.float64)
    n = len(poses)
    cov = np.broadcast_to(np.diag([0.03**2, 0.02**2, math.radians(0.1) ** 2]), (n, 3, 3))
    return Hypotheses(
        poses,
        poses + np.array([4.0, 0.5, 0.01]),
        np.linspace(0.8, 1.1, n),
        n_inliers=np.full(n, 60.0),
        reprojection_error_px=np.full(n, 1.2),
        joint=np.zeros(n, dtype=bool),
        pose_covariance=cov.copy(),
        entry_tags=tags,
    )


@pytest.fixture
def particles() -> np.ndarray:
    rng = np.random.default_rng(4)
    return np.column_stack(
        [rng.normal(10.0, 0.3, 400), rng.normal(5.0, 0.3, 400), rng.normal(0.1, 0.01, 400)]
    )


POSES = [[10.0, 5.0, 0.1], [10.2, 4.9, 0.105], [9.7, 5.3, 0.095], [10.05, 5.1, 0.1]]


def test_night_hypotheses_are_weighed_by_the_night_model(particles):
    model = DAY.with_condition("night", NIGHT)
    night = _hypotheses(POSES, [("night",), ("night", "rain"), ("night",), ("night",)])
    got = log_likelihood(particles, night, model)
    np.testing.assert_allclose(got, log_likelihood(particles, night, NIGHT), rtol=1e-12)
    assert np.abs(got - log_likelihood(particles, night, DAY)).max() > 1.0
    # untagged hypotheses (day entries, or an older server) keep the base model
    for tags in ([(), (), ("rain",), ()], None):
        day = _hypotheses(POSES, tags)
        np.testing.assert_allclose(
            log_likelihood(particles, day, model), log_likelihood(particles, day, DAY), rtol=1e-12
        )


def test_a_mixed_frame_sums_each_groups_mixture(particles):
    """Without the outlier floor the mixture is a sum over hypotheses: a frame with day and
    night hypotheses is the day model's density of the day ones plus the night model's of
    the night ones; the lost distance is the nearer of the two groups'."""
    model = DAY.with_condition("night", NIGHT)
    tags = [(), ("night",), (), ("night",)]
    mixed = _hypotheses(POSES, tags)
    day_part = mixed.subset(np.array([True, False, True, False]))
    night_part = mixed.subset(np.array([1, 3]))
    assert night_part.entry_tags == (("night",), ("night",))
    got, closest = log_likelihood_and_distance(particles, mixed, model)
    day_ll, day_closest = log_likelihood_and_distance(particles, day_part, DAY)
    night_ll, night_closest = log_likelihood_and_distance(particles, night_part, NIGHT)
    np.testing.assert_allclose(got, np.logaddexp(day_ll, night_ll), rtol=1e-10)
    assert closest == min(day_closest, night_closest)
    # the hypotheses' Gaussians (the refiner's view) follow the same split
    centres, covs = model.hypothesis_gaussians(mixed)
    c_night, s_night = NIGHT.hypothesis_gaussians(night_part)
    c_day, s_day = DAY.hypothesis_gaussians(day_part)
    np.testing.assert_allclose(centres[[1, 3]], c_night)
    np.testing.assert_allclose(covs[[1, 3]], s_night)
    np.testing.assert_allclose(centres[[0, 2]], c_day)
    np.testing.assert_allclose(covs[[0, 2]], s_day)


def test_the_outlier_floor_is_the_base_models(particles):
    floored = dataclasses.replace(DAY, outlier_log_density=-5.0)
    model = floored.with_condition("night", NIGHT)  # NIGHT has no floor
    far = _hypotheses([[60.0, 40.0, 1.0]], [("night",)])
    got = log_likelihood(particles, far, model)
    assert np.all(got >= -5.0) and np.all(got < -4.9)


def test_conditions_survive_the_stored_form_and_covariance_switch():
    model = DAY.with_condition("night", NIGHT).with_condition("rain", DAY)
    again = MeasurementModel.from_dict(model.to_dict())
    assert list(again.conditions) == ["night", "rain"]
    np.testing.assert_allclose(again.conditions["night"].Sigma1, NIGHT.Sigma1)
    assert again.conditions["night"].pnp.pixel_std_px == 2.5
    paper = again.with_covariance("paper")
    assert paper.covariance == "paper" and paper.conditions["night"].covariance == "paper"
    # a calibration stored before conditions existed loads without any
    stored = DAY.to_dict()
    del stored["conditions"]
    assert MeasurementModel.from_dict(stored).conditions == {}


def test_malformed_conditions_are_refused():
    nested = DAY.with_condition("night", NIGHT).to_dict()
    nested["conditions"]["night"]["conditions"] = {"rain": DAY.to_dict()}
    with pytest.raises(InvalidInputError, match="without conditions"):
        MeasurementModel.from_dict(nested)
    with pytest.raises(InvalidInputError, match="tag name"):
        MeasurementModel(conditions={" ": DAY})
    bad = DAY.to_dict()
    bad["conditions"] = {"night": {"mu1": [0, 0]}}
    with pytest.raises(InvalidInputError):
        MeasurementModel.from_dict(bad)
    with pytest.raises(InvalidInputError, match="entry_tags"):
        _hypotheses(POSES, [("night",)])


def test_a_subset_keeps_every_field():
    tags = [("night",), (), ("rain",), ()]
    hyps = dataclasses.replace(
        _hypotheses(POSES, tags), method=("ransac", "guided", "pooled", "joint")
    )
    sub = hyps.subset(np.array([2, 0]))
    assert sub.method == ("pooled", "ransac") and sub.entry_tags == (("rain",), ("night",))
    np.testing.assert_array_equal(sub.pose_world, hyps.pose_world[[2, 0]])
    np.testing.assert_array_equal(sub.pose_covariance, hyps.pose_covariance[[2, 0]])
    assert hyps.without_joint().method == ("ransac", "guided", "pooled", "joint")  # none joint
    with pytest.raises(InvalidInputError, match="method"):
        dataclasses.replace(hyps, method=("ransac",))

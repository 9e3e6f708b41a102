"""The retrieval vector's offset in the vehicle's frame: calibration and likelihood."""

import json
import math

import numpy as np
import pytest

from monoloc.core.calibration import (
    RETRIEVAL_MIN_STD_M,
    RETRIEVAL_MIN_STD_RAD,
    fit_measurement_model,
    retrieval_vectors,
)
from monoloc.core.errors import InvalidInputError
from monoloc.core.measurement import Hypotheses, MeasurementModel, log_likelihood


def _rotate(points: np.ndarray, angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    out = points.copy()
    out[..., 0] = c * points[..., 0] - s * points[..., 1]
    out[..., 1] = s * points[..., 0] + c * points[..., 1]
    if points.shape[-1] == 3:
        out[..., 2] = points[..., 2] + angle_rad
    return out


def test_vehicle_frame_offsets_are_along_and_across_the_query_heading():
    rng = np.random.default_rng(0)
    truth = np.column_stack([rng.uniform(-50, 50, (20, 2)), rng.uniform(-math.pi, math.pi, 20)])
    along, across = rng.uniform(-5, 5, 20), rng.uniform(-1, 1, 20)
    entry = truth.copy()
    entry[:, 0] += along * np.cos(truth[:, 2]) - across * np.sin(truth[:, 2])
    entry[:, 1] += along * np.sin(truth[:, 2]) + across * np.cos(truth[:, 2])
    vehicle = retrieval_vectors(np.full(20, 0.9), entry, truth, "vehicle")
    assert np.allclose(vehicle[:, 1], along) and np.allclose(vehicle[:, 2], across)
    world = retrieval_vectors(np.full(20, 0.9), entry, truth, "world")
    assert np.allclose(world[:, 1:3], entry[:, :2] - truth[:, :2])
    with pytest.raises(InvalidInputError):
        retrieval_vectors(np.full(20, 0.9), entry, truth, "compass")


def _one_drive_along_x(rng, n=400):
    """Training samples of one drive along +X split into its own map and queries: entries
    ahead and behind, none beside, all heading the same way."""
    truth = np.column_stack([rng.uniform(0, 300, n), np.zeros(n), np.zeros(n)])
    entry = truth + np.column_stack(
        [rng.uniform(-4, 4, n), rng.normal(0, 0.01, n), rng.normal(0, 1e-4, n)]
    )
    errors = rng.normal(size=(n, 3)) * [0.05, 0.05, 0.002]
    return errors, truth, entry, rng.normal(0.9, 0.05, n)


def test_a_model_calibrated_on_one_street_weighs_a_street_running_another_way_alike():
    rng = np.random.default_rng(1)
    errors, truth, entry, e_vlad = _one_drive_along_x(rng)
    models = {
        frame: fit_measurement_model(
            errors,
            retrieval_vectors(e_vlad, entry, truth, frame),
            outlier_log_density=None,
            retrieval_frame=frame,
        )
        for frame in ("world", "vehicle")
    }
    # the minimum spread: a later drive a lane to the side or turned a few degrees is not
    # ruled out by the training run (which had 1 cm and 0.006 deg)
    for model in models.values():
        assert np.linalg.eigvalsh(model.Sigma2[1:3, 1:3]).min() >= RETRIEVAL_MIN_STD_M**2 - 1e-9
        assert model.Sigma2[3, 3] >= RETRIEVAL_MIN_STD_RAD**2 - 1e-12
        assert np.linalg.eigvalsh(model.Sigma2).min() > 0.0
    # a drive that spreads more keeps its own spread
    assert models["vehicle"].Sigma2[1, 1] == pytest.approx(
        np.var(entry[:, 0] - truth[:, 0]), rel=0.05
    )
    # a query on the training street (heading +X) and the same scene turned by 90 deg
    # (a street running along +Y): entry 4 m ahead, hypothesis at the particle
    query = np.array([[10.0, 0.0, 0.0]])
    scene = {
        "hypothesis": query.copy(),
        "entry": np.array([[14.0, 0.0, 0.0]]),
    }
    ll = {}
    for frame, model in models.items():
        for turn in (0.0, math.pi / 2):
            hyp = Hypotheses(
                _rotate(scene["hypothesis"], turn), _rotate(scene["entry"], turn), np.array([0.9])
            )
            ll[frame, turn] = float(log_likelihood(_rotate(query, turn), hyp, model)[0])
    assert ll["vehicle", 0.0] == pytest.approx(ll["vehicle", math.pi / 2], abs=1e-9)
    # the world-frame Sigma2 remembers the training street's direction: 4 m across it is
    # 4 sigma of its floor, not a fraction of the along-street spread
    assert ll["world", 0.0] - ll["world", math.pi / 2] > 5.0


def test_the_retrieval_frame_round_trips_and_old_calibrations_are_world():
    model = MeasurementModel(retrieval_frame="vehicle")
    back = MeasurementModel.from_dict(json.loads(json.dumps(model.to_dict())))
    assert back.retrieval_frame == "vehicle"
    stored = model.to_dict()
    del stored["retrieval_frame"]
    assert MeasurementModel.from_dict(stored).retrieval_frame == "world"
    with pytest.raises(InvalidInputError):
        MeasurementModel(retrieval_frame="compass")


def test_the_minimum_spread_leaves_a_turning_drive_alone():
    rng = np.random.default_rng(2)
    n = 500
    samples = np.column_stack(
        [
            rng.normal(0.9, 0.05, n),
            rng.normal(0, 3.0, n),
            rng.normal(0, 2.0, n),
            rng.normal(0, 0.15, n),
        ]
    )
    model = fit_measurement_model(rng.normal(size=(n, 3)) * [0.05, 0.05, 0.002], samples)
    floor = np.diag(np.square([0.01, 0.05, 0.05, 1e-3]))  # the fit's own tiny floor
    assert np.allclose(model.Sigma2 - floor, np.cov(samples.T))

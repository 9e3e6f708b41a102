"""The localize answer's joint hypothesis and quality features on the wire: the server's
answer body, read back by the vehicle's client; answers of older servers still parse."""

import json

import numpy as np

from monoloc.client.api import LocalizeAnswer
from monoloc.core.geometry import T_world_from_cam_planar, planar_from_T_world_from_cam
from monoloc.core.measurement import MeasurementModel
from monoloc.server.api.convert import localize_response
from monoloc.server.api.schemas import CalibrationPublic
from monoloc.server.jobs.calibration import describe_calibration
from monoloc.server.localize import LocalizationResult, PoseHypothesis


def _hypothesis(entry_id, x_m, n_inliers, error_px, joint=False, members=()):
    T = T_world_from_cam_planar(x_m, 2.0, 0.1, 1.65)
    return PoseHypothesis(
        entry_id=entry_id,
        T_world_from_cam=T,
        pose_world=planar_from_T_world_from_cam(T),
        entry_pose_world=np.array([x_m + 1.0, 2.0, 0.1]),
        e_vlad=0.7 + entry_id / 100,
        n_matches=2 * n_inliers,
        n_inliers=n_inliers,
        reprojection_error_px=error_px,
        joint=joint,
        entry_ids=members,
        method="joint" if joint else "guided",
        covariance_px1=None if joint else _covariance(entry_id),
    )


def _covariance(entry_id):
    """A planar pose covariance at 1 px, different for each entry."""
    along, across = 0.01 * entry_id, 0.004 * entry_id
    C = np.diag([along**2, across**2, (1e-4 * entry_id) ** 2])
    C[0, 1] = C[1, 0] = 0.3 * along * across
    return C


def _body() -> dict:
    result = LocalizationResult(
        hypotheses=[
            _hypothesis(3, 10.0, 120, 0.9),
            _hypothesis(5, 10.1, 80, 1.2),
            _hypothesis(3, 10.04, 195, 0.8, joint=True, members=(3, 5)),
        ],
        retrieved_ids=np.array([3, 5]),
        retrieved_distances=np.array([0.73, 0.75]),
        rejected=[],
        n_features=1000,
        timings_ms={"total": 9.0},
    )
    response = localize_response(1, 7, result, result.timings_ms, seed=11)
    return json.loads(response.model_dump_json())


def test_joint_hypothesis_and_quality_features_round_trip():
    body = _body()
    assert body["hypotheses"][0]["joint"] and body["hypotheses"][0]["entry_ids"] == [3, 5]
    assert body["hypotheses"][0]["method"] == "joint"
    answer = LocalizeAnswer.from_json(body)
    hyps = answer.hypotheses
    assert len(hyps) == 3 and hyps.has_quality
    assert hyps.joint.tolist() == [True, False, False]
    assert hyps.n_inliers.tolist() == [195, 120, 80]
    assert np.allclose(hyps.reprojection_error_px, [0.8, 0.9, 1.2])
    assert np.allclose(hyps.pose_world[0, :2], [10.04, 2.0])
    # The best pose stays the best single entry's, as before the joint pose existed.
    assert np.allclose(answer.best_pose_world[:2], [10.0, 2.0])


def test_each_entry_pose_covariance_reaches_the_client():
    body = _body()
    assert body["hypotheses"][0]["pose_covariance"] is None  # the joint pose has none
    assert len(body["hypotheses"][1]["pose_covariance"]) == 9
    C = LocalizeAnswer.from_json(body).hypotheses.pose_covariance
    assert C.shape == (3, 3, 3) and np.isnan(C[0]).all()
    np.testing.assert_allclose(C[1], _covariance(3))
    np.testing.assert_allclose(C[2], _covariance(5))


def test_an_answer_of_an_older_server_still_parses():
    body = _body()
    for h in body["hypotheses"]:
        for key in ("joint", "entry_ids", "method", "n_inliers", "pose_covariance"):
            h.pop(key)
    body["hypotheses"] = body["hypotheses"][1:]
    hyps = LocalizeAnswer.from_json(body).hypotheses
    assert len(hyps) == 2 and not hyps.has_quality and hyps.joint is None
    assert hyps.pose_covariance is None


def test_a_calibration_stored_before_the_quality_model_is_still_served():
    stored = {
        "mu1": [0.02, -0.01, 0.001],
        "Sigma1": [[0.04, 0, 0], [0, 0.04, 0], [0, 0, 0.0007]],
        "mu2": [0.9, 0.0, 0.0, 0.0],
        "Sigma2": [[0.06, 0, 0, 0], [0, 64, 0, 0], [0, 0, 64, 0], [0, 0, 0, 0.27]],
        "outlier_log_density": -16.0,
        "source": "calibrated",
        "provenance": {"used": 1770},
        "updated_at": "2024-05-01T12:00:00+00:00",
    }
    model = MeasurementModel.from_dict(stored)
    public = CalibrationPublic(
        **{k: v for k, v in model.to_dict().items() if k != "source"},
        provenance=stored["provenance"],
        calibrated=True,
        source="calibrated",
    )
    assert public.covariance == "paper" and public.quality is None
    assert any("no quality-aware parameters" in line for line in describe_calibration(stored))
    # What the vehicle downloads loads as the same model.
    again = MeasurementModel.from_dict(json.loads(public.model_dump_json()))
    assert np.allclose(again.Sigma1, model.Sigma1) and again.quality is None

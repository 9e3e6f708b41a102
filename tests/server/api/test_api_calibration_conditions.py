"""Calibration conditions over HTTP: a calibration job with ``condition=night`` stores
its model, with its own provenance, as ``conditions.night`` beside the untouched base
calibration, and refuses a map without one (409, before the upload is kept); calibrating
the base again keeps the condition (same vocabulary); PUT takes conditions, checked like
the base (a condition with conditions of its own: 422); DELETE removes one (404 if
absent).

The training runs are the session's sim runs (16 frames each) with k = 3: the map run
stands for the base (day) run, the query run for the night run.
"""

from __future__ import annotations

from datetime import datetime

import numpy as np
import pytest
from api_helpers import CALIBRATION, tar_sequence, wait_job

from monoloc.core.measurement import MeasurementModel

TRAIN = {"format": "kitti", "k": "3"}
NIGHT = dict(
    mu1=[0.1, 0.0, 0.0],
    Sigma1=np.diag([0.3, 0.3, 0.001]).tolist(),
    mu2=[1.0, 0.0, 0.0, 0.0],
    Sigma2=np.diag([0.1, 64.0, 64.0, 0.5]).tolist(),
    provenance={"training_run": "sim-trainnight"},
)


@pytest.fixture
def app(empty_map_app):
    return empty_map_app


def _calibrate(client, keys, map_id, archive: bytes, **form):
    return client.post(
        f"/v1/maps/{map_id}/calibration/jobs",
        headers=keys.header("write"),
        data={**TRAIN, **form},
        files={"archive": ("train.tar.gz", archive, "x")},
    )


def _done(client, keys, accepted) -> dict:
    assert accepted.status_code == 202, accepted.text
    job = wait_job(client, accepted.json()["job"]["id"], keys.header("write"))
    assert job["state"] == "done", job
    return job


def _calibration(client, keys, map_id) -> dict:
    r = client.get(f"/v1/maps/{map_id}/calibration", headers=keys.header("localize"))
    assert r.status_code == 200, r.text
    return r.json()


def _base(calibration: dict) -> dict:
    return {k: v for k, v in calibration.items() if k != "conditions"}


def test_a_condition_needs_the_base_calibration_and_a_tag_name(app, sim_dataset):
    client, keys, map_id, data_dir = app
    night = tar_sequence(sim_dataset, "01")
    r = _calibrate(client, keys, map_id, night, condition="night")
    assert r.status_code == 409, r.text
    message = r.json()["error"]["message"]
    assert "no calibration" in message and "calibrate the map without a condition first" in message
    for bad in ("no good", "-night", "x" * 65):
        r = _calibrate(client, keys, map_id, night, condition=bad)
        assert r.status_code == 422 and "invalid tag" in r.json()["error"]["message"], r.text
    # refused before anything was kept: no job, no upload
    assert client.get("/v1/jobs", headers=keys.header("write")).json()["items"] == []
    assert not any((data_dir / "uploads").glob("*"))
    assert _calibration(client, keys, map_id)["calibrated"] is False


def test_a_night_condition_is_calibrated_beside_the_base_and_survives_it(app, sim_dataset):
    client, keys, map_id, _ = app
    day, night = tar_sequence(sim_dataset, "00"), tar_sequence(sim_dataset, "01")
    first = _done(client, keys, _calibrate(client, keys, map_id, day))
    base = _calibration(client, keys, map_id)
    assert base["calibrated"] and base["conditions"] == {} and first["result"]["conditions"] == []

    accepted = _calibrate(client, keys, map_id, night, condition="Night")  # lower-cased
    assert accepted.json()["job"]["params"]["condition"] == "night"
    job = _done(client, keys, accepted)
    got = _calibration(client, keys, map_id)
    assert _base(got) == _base(base)  # the base is untouched
    assert list(got["conditions"]) == ["night"]
    cond = got["conditions"]["night"]
    prov = cond["provenance"]
    assert prov["job_id"] == job["id"] and prov["condition"] == "night"
    assert prov["vocabulary_hash"] == base["provenance"]["vocabulary_hash"]
    assert prov["frames"] == 16 and cond["updated_at"] and cond["source"] == "calibrated"
    assert cond["Sigma1"] != base["Sigma1"]  # fitted on the night run, not copied
    assert job["result"]["condition"] == "night" and job["result"]["provenance"] == prov
    assert job["result"]["Sigma1"] == cond["Sigma1"]
    listed = client.get(f"/v1/maps/{map_id}", headers=keys.header("admin")).json()
    assert listed["calibrated"] and listed["calibrated_conditions"] == ["night"]
    model = MeasurementModel.from_dict(got)  # what a vehicle loads
    assert np.allclose(model.conditions["night"].Sigma1, cond["Sigma1"])

    # Calibrating the base again (same vocabulary) keeps the night model as it was.
    again = _done(client, keys, _calibrate(client, keys, map_id, day, seed="1"))
    rebased = _calibration(client, keys, map_id)
    assert rebased["provenance"]["job_id"] == again["id"]
    assert "conditions_dropped" not in rebased["provenance"]
    assert rebased["conditions"] == got["conditions"] and again["result"]["conditions"] == ["night"]


def test_put_takes_conditions_and_delete_removes_one(fresh):
    client, keys = fresh
    camera = dict(fx=300.0, fy=300.0, cx=159.5, cy=119.5, width_px=320, height_px=240)
    r = client.post("/v1/maps", json={"name": "c", "camera": camera}, headers=keys.header("admin"))
    url, w = f"/v1/maps/{r.json()['id']}/calibration", keys.header("write")
    # no calibration yet: no condition to delete
    gone = client.delete(f"{url}/conditions/night", headers=w)
    assert gone.status_code == 404 and "no calibration for condition 'night'" in gone.text

    put = client.put(url, headers=w, json=dict(CALIBRATION, conditions={"Night": NIGHT}))
    assert put.status_code == 200, put.text
    got = client.get(url, headers=keys.header("localize")).json()
    assert got["mu1"] == CALIBRATION["mu1"] and list(got["conditions"]) == ["night"]
    night = got["conditions"]["night"]
    assert night["mu1"] == NIGHT["mu1"] and night["provenance"] == NIGHT["provenance"]
    assert night["source"] == "put"
    assert datetime.fromisoformat(night["updated_at"]) == datetime.fromisoformat(got["updated_at"])
    assert MeasurementModel.from_dict(got).conditions["night"].Sigma1[0, 0] == 0.3

    # refused, the stored calibration kept: a condition with conditions of its own, a
    # condition with a bad covariance, a name that is no tag
    nested = dict(NIGHT, conditions={"rain": NIGHT})
    not_pd = dict(NIGHT, Sigma1=[[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    for conditions, words in (
        ({"night": nested}, "condition 'night': a condition's model cannot have conditions"),
        ({"night": not_pd}, "condition 'night': Sigma1 must be positive definite"),
        ({"no good": NIGHT}, "invalid tag"),
        ({"night": dict(NIGHT, provenance="lamp")}, "provenance must be an object"),
    ):
        refused = client.put(url, headers=w, json=dict(CALIBRATION, conditions=conditions))
        assert refused.status_code == 422, refused.text
        assert words in refused.json()["error"]["message"], refused.text
    assert client.get(url, headers=w).json()["conditions"] == got["conditions"]

    deleted = client.delete(f"{url}/conditions/night", headers=w)
    assert deleted.status_code == 200 and deleted.json()["conditions"] == {}
    after = client.get(url, headers=w).json()
    assert after["conditions"] == {} and after["mu1"] == CALIBRATION["mu1"]
    again = client.delete(f"{url}/conditions/night", headers=w)
    assert again.status_code == 404 and "conditions: none" in again.json()["error"]["message"]
    assert client.delete("/v1/maps/77/calibration/conditions/night", headers=w).status_code == 404
    assert (
        client.delete(f"{url}/conditions/night", headers=keys.header("localize")).status_code == 403
    )

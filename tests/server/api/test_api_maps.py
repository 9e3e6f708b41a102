"""Maps and calibration routes, the vehicle client against the app, and the OpenAPI
description (examples on every route)."""

from __future__ import annotations

import math

import numpy as np
from api_helpers import CALIBRATION, frame_png

from monoloc.client.api import MonolocClient
from monoloc.core.measurement import MeasurementModel

CAMERA = dict(fx=300.0, fy=300.0, cx=159.5, cy=119.5, width_px=320, height_px=240)


def test_map_lifecycle(fresh):
    client, keys = fresh
    admin = keys.header("admin")
    r = client.post("/v1/maps", json={"name": "city-1", "camera": CAMERA}, headers=admin)
    assert r.status_code == 201, r.text
    created = r.json()
    assert created["version"] == 0 and created["n_entries"] == 0 and not created["calibrated"]
    assert created["vocabulary"]["n_words"] == 64 and created["index_loaded"]
    map_id = created["id"]
    refusals = [
        ({"name": "city-1", "camera": CAMERA}, 409),
        ({"name": "bad name!", "camera": CAMERA}, 422),
        ({"name": "c2", "camera": {**CAMERA, "fx": -1}}, 422),
        ({"name": "c3", "camera": CAMERA, "vocabulary": "0123abcd0123abcd"}, 404),
        ({"name": "c3", "camera": CAMERA, "vocabulary": "0123abcd"}, 422),  # not a hash
        ({"name": "c4"}, 422),
    ]
    for body, status in refusals:
        r = client.post("/v1/maps", json=body, headers=admin)
        assert r.status_code == status, (body, r.text)
        assert set(r.json()["error"]) >= {"code", "message"}
    same_vocab = client.post(
        "/v1/maps",
        headers=admin,
        json={"name": "city-2", "camera": CAMERA, "vocabulary": created["vocabulary"]["hash"]},
    )
    assert same_vocab.json()["vocabulary"]["id"] == created["vocabulary"]["id"]

    listed = client.get("/v1/maps", headers=keys.header("localize")).json()["items"]
    assert [m["name"] for m in listed] == ["city-1", "city-2"]
    got = client.get(f"/v1/maps/{map_id}", headers=keys.header("localize")).json()
    assert got["camera"] == CAMERA and got["n_runs"] == 0 and got["tag_counts"] == {}

    index_file = client.app.state.monoloc.registry.index_path(map_id)
    assert index_file.exists()
    assert client.delete(f"/v1/maps/{map_id}", headers=admin).status_code == 204
    assert not index_file.exists()
    assert client.get(f"/v1/maps/{map_id}", headers=admin).status_code == 404
    assert client.delete(f"/v1/maps/{map_id}", headers=admin).status_code == 404
    assert client.get("/v1/maps/99", headers=admin).json()["error"]["code"] == "not_found"


def test_a_map_says_how_its_entries_picked_their_corners(tmp_path):
    """A new map records the server's ORB rule and says it is current; a map whose entries
    were picked by ORB's own rule (every map from before the grid) says it is not."""
    from api_helpers import ADMIN_KEY, make_settings, open_client
    from sqlalchemy import update

    from monoloc.server.storage.db import create_engine_for
    from monoloc.server.storage.models import Map

    settings = make_settings(tmp_path / "data")
    admin = {"X-API-Key": ADMIN_KEY}
    with open_client(settings) as client:
        r = client.post("/v1/maps", json={"name": "grid", "camera": CAMERA}, headers=admin)
        assert r.status_code == 201, r.text
        created = r.json()
        assert created["features"] == {
            "rule": "grid",
            "grid_cells": [8, 5],
            "candidates_factor": 2.0,
            "fast_thresholds": [20, 12],
            "flat_fast_corners": 150,
        }
        assert created["features_current"] is True
        engine = create_engine_for(settings)
        with engine.begin() as conn:
            conn.execute(
                update(Map).where(Map.id == created["id"]).values(features={"rule": "strongest"})
            )
        engine.dispose()
        old = client.get(f"/v1/maps/{created['id']}", headers=admin).json()
        assert old["features"] == {"rule": "strongest"} and old["features_current"] is False
        listed = client.get("/v1/maps", headers=admin).json()
        assert [m["features_current"] for m in listed["items"]] == [False]


def test_calibration_defaults_put_and_delete(fresh):
    client, keys = fresh
    map_id = client.post(
        "/v1/maps", json={"name": "c", "camera": CAMERA}, headers=keys.header("admin")
    ).json()["id"]
    url, w = f"/v1/maps/{map_id}/calibration", keys.header("write")
    default = client.get(url, headers=keys.header("localize")).json()
    reference = MeasurementModel().to_dict()
    assert default["calibrated"] is False and default["source"] == "defaults"
    assert np.allclose(default["Sigma1"], reference["Sigma1"])

    put = client.put(url, headers=w, json=CALIBRATION)
    assert put.status_code == 200, put.text
    got = client.get(url, headers=keys.header("localize")).json()
    assert got["calibrated"] and got["source"] == "put" and got["updated_at"]
    assert got["provenance"] == CALIBRATION["provenance"]
    assert np.allclose(got["Sigma2"], CALIBRATION["Sigma2"]) and got["mu1"] == CALIBRATION["mu1"]
    assert client.get(f"/v1/maps/{map_id}", headers=w | keys.header("admin")).json()["calibrated"]
    # A body's offsets are in the product's frame (along / across the vehicle's heading),
    # the only one it may name, stored so; the lab's variants (the paper's world axes, the
    # quality covariance) are refused with the field named, in a condition too. Without
    # pnp parameters the paper's covariance is selected.
    assert got["retrieval_frame"] == "vehicle" and got["covariance"] == "paper"
    vehicle = dict(CALIBRATION, retrieval_frame="vehicle")
    assert client.put(url, headers=w, json=vehicle).json()["retrieval_frame"] == "vehicle"
    for lab in ({"retrieval_frame": "world"}, {"retrieval_frame": "compass"}):
        refused = client.put(url, headers=w, json=dict(CALIBRATION, **lab))
        assert refused.status_code == 422 and "retrieval_frame" in refused.text
    refused = client.put(url, headers=w, json=dict(CALIBRATION, covariance="quality"))
    assert refused.status_code == 422 and "covariance" in refused.text
    night = {k: v for k, v in CALIBRATION.items() if k != "provenance"}
    for lab in ({"retrieval_frame": "world"}, {"covariance": "quality"}):
        body = dict(CALIBRATION, conditions={"night": {**night, **lab}})
        refused = client.put(url, headers=w, json=body)
        assert refused.status_code == 422 and f"conditions.night.{next(iter(lab))}" in refused.text
    # The paper covariance's tail: none unless given; given, served and used by the
    # vehicle; out of range refused with the field named, the stored one kept.
    assert (got["tail_weight"], got["tail_scale"]) == (0.0, 1.0)
    tailed = dict(CALIBRATION, tail_weight=0.3, tail_scale=10.0)
    assert client.put(url, headers=w, json=tailed).json()["tail_weight"] == 0.3
    assert client.get(url, headers=w).json()["tail_scale"] == 10.0
    for bad in ({"tail_weight": 1.0}, {"tail_weight": -0.1}, {"tail_scale": 0.5}):
        refused = client.put(url, headers=w, json=dict(CALIBRATION, **bad))
        assert refused.status_code == 422 and next(iter(bad)) in refused.text
    assert client.get(url, headers=w).json()["tail_weight"] == 0.3
    # The PnP covariance model: stored, served, and read back by the vehicle's model (the
    # product's, selected when its parameters are given unless the body says paper);
    # selected without its parameters, or with a non-positive floor, refused.
    pnp = {
        "mu1": [0.01, 0.0, 0.0],
        "pixel_std_px": 1.4,
        "floor": [[4e-4, 0.0, 0.0], [0.0, 2e-4, 0.0], [0.0, 0.0, 1e-6]],
        "outlier_weight": 0.3,
    }
    stored = client.put(url, headers=w, json=dict(CALIBRATION, pnp=pnp, covariance="pnp"))
    assert stored.status_code == 200, stored.text
    served = client.get(url, headers=keys.header("localize")).json()
    assert served["covariance"] == "pnp" and served["pnp"]["pixel_std_px"] == 1.4
    assert MeasurementModel.from_dict(served).pnp.floor[1, 1] == 2e-4
    unsaid = client.put(url, headers=w, json=dict(CALIBRATION, pnp=pnp)).json()
    assert unsaid["covariance"] == "pnp"
    paper = client.put(url, headers=w, json=dict(CALIBRATION, pnp=pnp, covariance="paper"))
    assert paper.json()["covariance"] == "paper" and paper.json()["pnp"]["pixel_std_px"] == 1.4
    assert client.put(url, headers=w, json=dict(CALIBRATION, pnp=pnp)).status_code == 200
    no_params = client.put(url, headers=w, json=dict(CALIBRATION, covariance="pnp"))
    assert no_params.status_code == 422 and "pnp" in no_params.text
    bad_floor = dict(pnp, floor=[[-1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    refused = client.put(url, headers=w, json=dict(CALIBRATION, pnp=bad_floor))
    assert refused.status_code == 422
    assert client.get(url, headers=w).json()["covariance"] == "pnp"

    not_pd = dict(CALIBRATION, Sigma1=[[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    asymmetric = dict(CALIBRATION, Sigma1=[[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    short = dict(CALIBRATION, mu2=[0.0, 1.0])
    for body in (not_pd, asymmetric, short):
        assert client.put(url, headers=w, json=body).status_code == 422
    assert client.get(url, headers=w | keys.header("admin")).json()["mu1"] == CALIBRATION["mu1"]

    # Calibration jobs take an uploaded training run (test_api_calibration_job.py).
    assert client.post(f"{url}/jobs", headers=w, json={"run_id": 1}).status_code == 422
    assert client.delete(url, headers=w).json()["calibrated"] is False
    assert client.put("/v1/maps/77/calibration", headers=w, json=CALIBRATION).status_code == 404


def test_a_calibration_stored_with_the_labs_variants_is_still_served(fresh, tmp_path):
    """A calibration an older server stored selecting the quality covariance with the
    offsets in world axes (for a night condition too): served as stored and loaded by the
    vehicle as such, though a body naming them is refused."""
    from api_helpers import make_settings

    from monoloc.core.measurement import QualityModel
    from monoloc.server.calibration_conditions import condition_entry
    from monoloc.server.storage import maps as maps_repo
    from monoloc.server.storage.db import create_engine_for, make_session_factory, session_scope

    client, keys = fresh
    map_id = client.post(
        "/v1/maps", json={"name": "old", "camera": CAMERA}, headers=keys.header("admin")
    ).json()["id"]
    lab = MeasurementModel(
        quality=QualityModel(), covariance="quality", retrieval_frame="world", source="calibrated"
    )
    night = condition_entry(lab, {"job_id": 2}, "2026-11-20T10:00:00+00:00")
    stored = {**lab.to_dict(), "provenance": {"job_id": 1}, "conditions": {"night": night}}
    engine = create_engine_for(make_settings(tmp_path / "data"))
    with session_scope(make_session_factory(engine)) as session:
        maps_repo.set_calibration(session, map_id, stored)
    engine.dispose()

    url = f"/v1/maps/{map_id}/calibration"
    served = client.get(url, headers=keys.header("localize"))
    assert served.status_code == 200, served.text
    got = served.json()
    assert (got["covariance"], got["retrieval_frame"], got["calibrated"]) == (
        "quality", "world", True
    )  # fmt: skip
    assert got["quality"]["n_ref"] == 100.0 and got["provenance"] == {"job_id": 1}
    assert got["conditions"]["night"]["covariance"] == "quality"
    vehicle = MonolocClient("http://testserver", keys.localize, transport=client._transport)
    model, calibrated = vehicle.measurement_model(map_id)
    assert calibrated and (model.covariance, model.retrieval_frame) == ("quality", "world")
    assert model.conditions["night"].retrieval_frame == "world"
    put_back = {k: v for k, v in got.items() if k not in ("calibrated", "source", "updated_at")}
    assert client.put(url, headers=keys.header("write"), json=put_back).status_code == 422


def test_vehicle_client_reads_calibration_and_localizes(sim_dataset, map_copy, client_on_copy):
    client, m = client_on_copy, map_copy
    client.put(f"/v1/maps/{m.map_id}/calibration", headers=m.keys.header("write"), json=CALIBRATION)
    vehicle = MonolocClient("http://testserver", m.keys.localize, transport=client._transport)
    assert vehicle.find_map_id("street") == m.map_id
    model, calibrated = vehicle.measurement_model(m.map_id)
    assert calibrated and np.allclose(model.mu2, CALIBRATION["mu2"])
    answer = vehicle.localize(m.map_id, frame_png(sim_dataset, "01", 9), k=5)
    assert len(answer.hypotheses) >= 1 and answer.map_version == m.job["result"]["map_version"]
    assert all(math.isfinite(v) for v in answer.timings_ms.values())
    # every per-entry hypothesis comes with its PnP pose covariance (at 1 px), positive
    # definite, and the vehicle's pnp model can weigh with it
    hyps = answer.hypotheses
    per_entry = ~hyps.joint & np.array([m != "pooled" for m in _methods(answer)])
    assert per_entry.any()
    for C in hyps.pose_covariance[per_entry]:
        assert np.all(np.isfinite(C)) and np.linalg.eigvalsh(C).min() > 0.0


def _methods(answer) -> list[str]:
    return [h.get("method", "ransac") for h in answer.raw["hypotheses"]]


def _has_example(node) -> bool:
    if isinstance(node, dict):
        if "example" in node or "examples" in node:
            return True
        return any(_has_example(v) for v in node.values())
    if isinstance(node, list):
        return any(_has_example(v) for v in node)
    return False


def test_openapi_has_an_example_on_every_route_and_documents_the_key(fresh):
    client, _ = fresh
    spec = client.get("/openapi.json").json()
    schemas = spec["components"]["schemas"]

    def resolve(node):
        if isinstance(node, dict):
            if "$ref" in node:
                return resolve(schemas[node["$ref"].rsplit("/", 1)[1]])
            return {k: resolve(v) for k, v in node.items() if k != "ValidationError"}
        if isinstance(node, list):
            return [resolve(v) for v in node]
        return node

    operations = [
        (path, method, op) for path, item in spec["paths"].items() for method, op in item.items()
    ]
    assert len(operations) >= 28
    for path, method, op in operations:
        success = {k: v for k, v in op["responses"].items() if k.startswith("2")}
        documented = _has_example(resolve(op.get("requestBody", {}))) or _has_example(
            resolve(success)
        )
        assert documented or set(success) == {"204"}, (method, path)
        assert _has_example(resolve(op["responses"].get("401", {}))) or path in (
            "/healthz",
            "/readyz",
        ), (method, path)
        assert op.get("summary"), (method, path)
    assert "/v1/maps/{map_id}/stream" in spec["info"]["description"]
    schemes = spec["components"]["securitySchemes"]
    assert schemes["APIKeyHeader"]["name"] == "X-API-Key"
    assert "X-API-Key" in spec["info"]["description"]

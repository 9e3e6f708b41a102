"""What one request may cost is bounded before work starts (issue 50): the rule walked
over the whole OpenAPI description (every parameter bounded, every body limited, every
API route on an admission lane), and the coverage route's own limits."""

from __future__ import annotations

import re
import resource
import time

import pytest
from api_helpers import make_settings, open_client

from monoloc.server.api.admission import lane_of
from monoloc.server.api.console import routes as console_routes

NO_LANE = {"/healthz", "/readyz", "/metrics"}  # always answer: probes and scrapers


def _branches(schema: dict) -> list[dict]:
    options = schema.get("anyOf") or schema.get("oneOf") or [schema]
    return [s for s in options if s.get("type") != "null"]


def _unbounded(schema: dict) -> str | None:
    for branch in _branches(schema):
        kind = branch.get("type")
        if kind in ("integer", "number"):
            low = "minimum" in branch or "exclusiveMinimum" in branch
            high = "maximum" in branch or "exclusiveMaximum" in branch
            if not (low and high):
                return f"{kind} without both bounds"
        elif kind == "array":
            if "maxItems" not in branch:
                return "array without maxItems"
            problem = _unbounded(branch.get("items", {}))
            if problem:
                return f"items: {problem}"
        elif kind == "string":
            if not ({"maxLength", "pattern", "enum", "const"} & set(branch)):
                return "string without maxLength, pattern or enum"
    return None


def _operations(spec: dict):
    for path, operations in spec["paths"].items():
        for method, operation in operations.items():
            yield path, method.upper(), operation


def test_every_operation_is_bounded_before_its_work_starts(tmp_path):
    with open_client(make_settings(tmp_path / "d")) as client:
        spec = client.get("/openapi.json").json()
    problems = []
    for path, method, operation in _operations(spec):
        concrete = re.sub(r"\{[^}]+\}", "1", path)
        if path not in NO_LANE and lane_of(method, concrete) is None:
            problems.append(f"{method} {path}: no admission lane")
        for parameter in operation.get("parameters", []):
            problem = _unbounded(parameter.get("schema", {}))
            if problem:
                problems.append(f"{method} {path} {parameter['name']}: {problem}")
        if "requestBody" in operation:
            limit = operation.get("x-monoloc-body-limit") or {}
            if not isinstance(limit.get("max_bytes"), int):
                problems.append(f"{method} {path}: body without a stated limit")
    assert problems == [], "\n".join(problems)


@pytest.mark.parametrize(
    "radius", ["1e-6", "5e-324", "0.0002", "0.00005", "0", "-1", "0.09", "nan", "inf", "1e309"]
)
def test_coverage_refuses_a_radius_below_its_minimum_at_once(client_on_copy, map_copy, radius):
    """radius_m=1e-6 once sampled the route every 0.25 um (23.5 GB); 0.0002 answered 29 MB
    (0.63 GB of memory), 0.00005 117 MB; 5e-324 made a zero step and a 500. All are 422
    now, in milliseconds and without memory growth."""
    headers = map_copy.keys.header("localize")
    path = f"/v1/maps/{map_copy.map_id}/coverage"
    # the route's first answer on a new app costs its own start-up; then the same app's
    # read of the map is the baseline: a loaded machine slows both, sampling only one
    warm = client_on_copy.get(path, params={"radius_m": "0.05"}, headers=headers)
    assert warm.status_code == 422, warm.text
    started = time.perf_counter()
    assert client_on_copy.get(f"/v1/maps/{map_copy.map_id}", headers=headers).status_code == 200
    baseline_s = time.perf_counter() - started
    rss_before_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    started = time.perf_counter()
    answer = client_on_copy.get(path, params={"radius_m": radius}, headers=headers)
    elapsed_s = time.perf_counter() - started
    assert answer.status_code == 422, answer.text
    assert elapsed_s < 1.0 + 2 * baseline_s, (elapsed_s, baseline_s)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss_before_kb < 100_000
    if radius in ("1e-6", "5e-324", "0.0002", "0.00005", "0.09"):
        assert "0.1" in answer.json()["error"]["message"]


def test_coverage_answers_within_its_sample_and_point_limits(client_on_copy, map_copy, monkeypatch):
    headers = map_copy.keys.header("localize")
    path = f"/v1/maps/{map_copy.map_id}/coverage"
    # nothing selected: the whole route is one gap per run, sampled every 2.5 cm
    params = {"radius_m": 0.1, "tag": "none-such"}
    whole = client_on_copy.get(path, params=params, headers=headers)
    assert whole.status_code == 200, whole.text
    body = whole.json()
    assert body["step_m"] == pytest.approx(0.025) and body["thinned"] is False
    points = sum(len(g["x_m"]) for g in body["gaps"])
    assert points > 40 and body["gap_length_m"] == pytest.approx(body["route_length_m"], 0.01)

    monkeypatch.setattr(console_routes, "MAX_POINTS", 20)
    thinned = client_on_copy.get(path, params=params, headers=headers).json()
    assert thinned["thinned"] is True
    assert sum(len(g["x_m"]) for g in thinned["gaps"]) <= 20
    assert thinned["gap_length_m"] == body["gap_length_m"]

    monkeypatch.setattr(console_routes, "MAX_SAMPLES", points // 2)
    refused = client_on_copy.get(path, params=params, headers=headers)
    assert refused.status_code == 422, refused.text
    message = refused.json()["error"]["message"]
    assert f"limit of {points // 2} samples" in message and "use radius_m >=" in message
    # the radius it names is answered
    least = float(message.rsplit(">=", 1)[1])
    again = client_on_copy.get(path, params={**params, "radius_m": least}, headers=headers)
    assert again.status_code == 200, again.text


def test_json_bodies_are_standard_json_with_known_fields_only(client_on_copy, map_copy):
    """{"tags": ["a"], "x": Infinity} was answered 200: a non-standard token and an
    unknown field, both ignored."""
    headers = {**map_copy.keys.header("write"), "Content-Type": "application/json"}
    listed = client_on_copy.get(f"/v1/maps/{map_copy.map_id}/entries", headers=headers).json()
    path = f"/v1/maps/{map_copy.map_id}/entries/{listed['items'][0]['id']}"
    for body in ('{"tags": ["a"], "x": Infinity}', '{"tags": ["a"], "x": 1}', '{"tags": NaN}'):
        answer = client_on_copy.patch(path, content=body, headers=headers)
        assert answer.status_code == 422, (body, answer.text)
    assert client_on_copy.patch(path, content='{"tags": ["a"]}', headers=headers).status_code == 200
    admin = {**map_copy.keys.header("admin"), "Content-Type": "application/json"}
    key = client_on_copy.post(
        "/v1/keys", content='{"name": "c", "scopes": ["localize"], "x": -Infinity}', headers=admin
    )
    assert key.status_code == 422, key.text


def test_nested_objects_refuse_unknown_fields_too(fresh):
    """The fuzzer's POST /v1/maps with junk keys inside ``camera`` was answered 201."""
    from api_helpers import camera_of

    client, keys = fresh
    admin = keys.header("admin")
    camera = {**camera_of(None), "M": [1, ["x"]]}
    made = client.post("/v1/maps", json={"name": "junk", "camera": camera}, headers=admin)
    assert made.status_code == 422, made.text
    assert "camera.M" in made.json()["error"]["message"]
    assert client.get("/v1/maps", headers=admin).json()["items"] == []
    made = client.post("/v1/maps", json={"name": "m", "camera": camera_of(None)}, headers=admin)
    assert made.status_code == 201, made.text
    origin = {"lat_deg": 1.0, "lon_deg": 2.0, "x_axis_heading_deg": 0.0, "zone": 32}
    path = f"/v1/maps/{made.json()['id']}/geo-reference"
    answer = client.put(path, json={"origin": origin}, headers=admin)
    assert answer.status_code == 422 and "origin.zone" in answer.json()["error"]["message"]
    assert client.get(path, headers=admin).status_code == 404  # nothing stored
    spec = client.get("/openapi.json").json()["components"]["schemas"]
    assert spec["Camera"]["additionalProperties"] is False
    assert spec["GeoOriginSpec"]["additionalProperties"] is False


def test_integers_are_json_numbers_without_a_fraction(fresh):
    """JSON Schema's integer takes 1241.0; the strict models refused it (422) though
    the OpenAPI allowed it. They take it now, and still refuse a fraction, true and a
    string."""
    from api_helpers import camera_of

    client, keys = fresh
    admin = keys.header("admin")
    for n, width in enumerate((1241.5, True, "1241")):
        camera = {**camera_of(None), "width_px": width}
        body = {"name": f"no{n}", "camera": camera}
        assert client.post("/v1/maps", json=body, headers=admin).status_code == 422, width
    camera = {**camera_of(None), "width_px": 1241.0, "height_px": 376.0}
    made = client.post("/v1/maps", json={"name": "whole", "camera": camera}, headers=admin)
    assert made.status_code == 201, made.text
    assert made.json()["camera"]["width_px"] == 1241 and made.json()["camera"]["height_px"] == 376
    key = {"name": "car", "scopes": ["localize"], "maps": [float(made.json()["id"])]}
    created = client.post("/v1/keys", json=key, headers=admin)
    assert created.status_code == 201 and created.json()["maps"] == [made.json()["id"]]
    assert client.post("/v1/keys", json={**key, "maps": [1.5]}, headers=admin).status_code == 422


def test_allow_lists_only_what_is_served(fresh):
    client, keys = fresh
    answer = client.request("PUT", "/v1/keys/me", headers=keys.header("admin"))
    assert answer.status_code == 405
    assert answer.headers["Allow"] == "GET, HEAD"
    answer = client.request("PUT", "/v1/keys/5", headers=keys.header("admin"))
    assert answer.headers["Allow"] == "DELETE"
    # OPTIONS /v1/keys/me advertised an undocumented DELETE (issue 50)
    answer = client.request("OPTIONS", "/v1/keys/me", headers=keys.header("admin"))
    assert answer.status_code == 405, answer.text
    assert answer.headers["Allow"] == "GET, HEAD"

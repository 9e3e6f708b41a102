"""Hostile requests that fuzzing found (issue 15): ids beyond the database's integers,
bodies sent without a key or larger than the route needs, and an OpenAPI description
looser than the server. Each test fails on the code before the fix."""

from __future__ import annotations

import re

import pytest
from api_helpers import ADMIN_KEY, camera_of

from monoloc.server.api.params import DB_ID_MAX

TOO_BIG = DB_ID_MAX + 1  # 2^63: the SQLite driver cannot hold it


def _operations(client) -> list[tuple[str, str, dict]]:
    spec = client.get("/openapi.json").json()
    return [(path, method, op) for path, ops in spec["paths"].items() for method, op in ops.items()]


def test_every_numeric_path_and_query_parameter_refuses_ids_beyond_int64(fresh):
    client, _ = fresh
    headers = {"X-API-Key": ADMIN_KEY}
    checked = 0
    for path, method, op in _operations(client):
        params = op.get("parameters", [])
        integers = [p for p in params if p["schema"].get("type") == "integer"]
        integers += [
            p
            for p in params
            if any(s.get("type") == "integer" for s in p["schema"].get("anyOf", []))
        ]
        for param in integers:
            if param["name"] in ("limit", "k"):
                continue
            url = re.sub(r"\{[^}]+\}", "1", path.replace("{" + param["name"] + "}", str(TOO_BIG)))
            query = {param["name"]: TOO_BIG} if param["in"] == "query" else None
            extra = {param["name"]: str(TOO_BIG)} if param["in"] == "header" else {}
            r = client.request(method, url, params=query, headers={**headers, **extra})
            assert r.status_code == 422, (method, url, param["name"], r.text)
            assert param["name"] in r.json()["error"]["message"]
            schema = param["schema"]
            bounds = schema if "maximum" in schema else schema["anyOf"][0]
            assert bounds["maximum"] == DB_ID_MAX, (path, param["name"])
            checked += 1
    assert checked >= 15  # every route with an id, the paging offsets, the list filters


def _asgi_post(client, path: str, headers: dict[str, str], body_chunks: int):
    """POST through the ASGI interface with a body source that records every read."""
    reads = []

    async def receive():
        reads.append(1)
        more = len(reads) < body_chunks
        return {"type": "http.request", "body": b"x" * 65536, "more_body": more}

    sent = []

    async def send(message):
        sent.append(message)

    raw = [(k.lower().encode(), v.encode()) for k, v in headers.items()]
    scope = {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": "POST",
        "scheme": "http",
        "path": path,
        "raw_path": path.encode(),
        "query_string": b"",
        "root_path": "",
        "headers": raw,
        "client": ("127.0.0.1", 1),
        "server": ("testserver", 80),
        "state": {},
    }

    async def call():
        await client.app(scope, receive, send)

    client.portal.call(call)
    start = next(m for m in sent if m["type"] == "http.response.start")
    return start["status"], len(reads)


@pytest.mark.parametrize(
    "path",
    ["/v1/maps/1/localize", "/v1/maps/1/entries", "/v1/maps/1/runs", "/v1/keys", "/v1/maps"],
)
def test_requests_without_a_valid_key_are_refused_before_their_body_is_read(fresh, path):
    client, keys = fresh
    multipart = {"content-type": "multipart/form-data; boundary=b", "content-length": "6553600"}
    status, reads = _asgi_post(client, path, multipart, body_chunks=100)
    assert (status, reads) == (401, 0)
    status, reads = _asgi_post(client, path, {**multipart, "x-api-key": "mlk_" + "x" * 43}, 100)
    assert (status, reads) == (401, 0)
    if path != "/v1/keys" and path != "/v1/maps":  # a vehicle key on a map:write route
        other = "write" if path.endswith("localize") else "localize"
        status, reads = _asgi_post(client, path, {**multipart, **keys.header(other)}, 100)
        assert (status, reads) == (403, 0)


def test_each_route_has_its_own_body_limit(fresh):
    client, keys = fresh
    settings = client.app.state.monoloc.settings
    big = b"\x89PNG\r\n\x1a\n" + b"\x00" * (settings.max_query_body_bytes + 1)
    r = client.post("/v1/maps/1/localize", files={"image": big}, headers=keys.header("localize"))
    assert r.status_code == 413 and "route's limit" in r.json()["error"]["message"]
    r = client.post(
        "/v1/keys",
        content=b'{"name": "' + b"a" * settings.max_json_body_bytes + b'"}',
        headers={**keys.header("admin"), "content-type": "application/json"},
    )
    assert r.status_code == 413
    # The same bytes are fine as a recorded run (an archive): refused for what they are.
    r = client.post(
        "/v1/maps/1/runs",
        files={"archive": ("a.tar", big, "application/x-tar")},
        data={"format": "kitti"},
        headers=keys.header("write"),
    )
    assert r.status_code in (404, 415), r.text  # no map 1 / not an archive, never 413
    limits = {
        (path, method): op.get("x-monoloc-body-limit", {}).get("max_bytes")
        for path, method, op in _operations(client)
    }
    assert limits["/v1/maps/{map_id}/localize", "post"] == settings.max_query_body_bytes
    assert limits["/v1/maps/{map_id}/entries", "post"] == settings.max_entry_body_bytes
    assert limits["/v1/maps/{map_id}/runs", "post"] == settings.max_body_bytes


def test_chunked_body_over_the_route_limit_is_cut_off(fresh):
    client, keys = fresh
    limit = client.app.state.monoloc.settings.max_json_body_bytes

    def chunks():
        yield b'{"name": "'
        for _ in range(limit // 65536 + 2):
            yield b"a" * 65536
        yield b'"}'

    r = client.post(
        "/v1/keys",
        content=chunks(),
        headers={**keys.header("admin"), "content-type": "application/json"},
    )
    assert r.status_code == 413


def _schema(spec: dict, name: str) -> dict:
    return spec["components"]["schemas"][name]


def test_openapi_states_the_patterns_and_shapes_the_server_enforces(fresh):
    client, keys = fresh
    spec = client.get("/openapi.json").json()
    name = _schema(spec, "MapCreate")["properties"]["name"]
    tag = _schema(spec, "TagsUpdate")["properties"]["tags"]["items"]
    assert re.search(name["pattern"], "kitti-00") and not re.search(name["pattern"], "")
    assert not re.search(name["pattern"], "-bad") and not re.search(name["pattern"], "a b")
    assert re.search(tag["pattern"], "off-center") and not re.search(tag["pattern"], "")
    calibration = _schema(spec, "CalibrationUpdate")["properties"]
    for key, n in (("Sigma1", 3), ("Sigma2", 4)):
        rows = calibration[key]
        assert rows["minItems"] == rows["maxItems"] == n
        assert rows["items"]["minItems"] == rows["items"]["maxItems"] == n
    admin = keys.header("admin")
    body = {"name": "", "camera": camera_of(None)}
    assert client.post("/v1/maps", json=body, headers=admin).status_code == 422
    r = client.post("/v1/maps", json={**body, "name": "m"}, headers=admin)
    assert r.status_code == 201, r.text
    map_id = r.json()["id"]
    r = client.patch(f"/v1/maps/{map_id}/entries/1", json={"tags": [""]}, headers=admin)
    assert r.status_code == 422 and "invalid tag" in r.json()["error"]["message"]


def test_types_are_strict_in_json_bodies(fresh):
    client, keys = fresh
    admin = keys.header("admin")
    map_id = client.post(
        "/v1/maps", json={"name": "m", "camera": camera_of(None)}, headers=admin
    ).json()["id"]
    good = {
        "mu1": [0.0, 0.0, 0.0],
        "Sigma1": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
        "mu2": [0.0, 0.0, 0.0, 0.0],
        "Sigma2": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
    }
    url = f"/v1/maps/{map_id}/calibration"
    for bad in (
        {"outlier_log_density": False},
        {"outlier_log_density": "-3"},
        {"mu1": [True, 0.0, 0.0]},
        {"Sigma1": [[1, 0], [0, 1, 0], [0, 0, 1]]},
    ):
        r = client.put(url, json={**good, **bad}, headers=admin)
        assert r.status_code == 422, (bad, r.text)
    r = client.put(url, json={**good, "outlier_log_density": -3}, headers=admin)
    assert r.status_code == 200 and r.json()["outlier_log_density"] == -3.0
    cam = {**camera_of(None), "width_px": True}
    assert (
        client.post("/v1/maps", json={"name": "n", "camera": cam}, headers=admin).status_code == 422
    )


def test_405_lists_every_allowed_method(fresh):
    client, keys = fresh
    r = client.put("/v1/maps/1", headers=keys.header("admin"))
    assert r.status_code == 405
    assert set(r.headers["allow"].split(", ")) == {"GET", "HEAD", "DELETE"}
    r = client.delete("/v1/maps/1/entries", headers=keys.header("admin"))
    assert set(r.headers["allow"].split(", ")) == {"GET", "HEAD", "POST"}
    r = client.post("/v1/maps/1/entries/2", headers=keys.header("admin"))
    assert set(r.headers["allow"].split(", ")) == {"GET", "HEAD", "DELETE", "PATCH"}


def test_malformed_bodies_answer_a_documented_status(fresh):
    client, keys = fresh
    spec = client.get("/openapi.json").json()
    r = client.post(
        "/v1/maps/1/localize",
        content=b"--zz\r\nbroken",
        headers={**keys.header("localize"), "content-type": "multipart/form-data"},
    )
    assert str(r.status_code) in spec["paths"]["/v1/maps/{map_id}/localize"]["post"]["responses"]
    r = client.post(
        "/v1/keys",
        content=b"{",
        headers={**keys.header("admin"), "content-type": "application/json"},
    )
    assert str(r.status_code) in spec["paths"]["/v1/keys"]["post"]["responses"]
    for path, method, op in _operations(client):
        if "requestBody" in op:
            assert {"400", "413", "422"} <= set(op["responses"]), (method, path)

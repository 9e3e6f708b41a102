"""The scope matrix, enumerated from app.routes: every route but the documented exempt
ones answers 401 without a key (or with an unknown one) and 403 with a key lacking its
scope, and lets a key with the scope through (whatever it answers then)."""

from __future__ import annotations

import re

import pytest
from api_helpers import ADMIN_KEY, TestClient, create_keys, make_settings, open_client
from fastapi.routing import APIRoute, APIWebSocketRoute
from starlette.testclient import WebSocketDenialResponse

EXEMPT = {"/healthz", "/readyz", "/docs", "/docs/oauth2-redirect", "/redoc", "/openapi.json"}
# the console's page and the docs' assets (no data; the page's API calls send the key)
EXEMPT |= {"/docs/assets", "/ui", "/ui/assets", "/ui/vendor/plotly.min.js"}
# "read" (what a map looks like) is granted to a valid key of any scope: no wrong key
WRONG_KEYS = {
    "localize": ["write"],
    "map:write": ["localize"],
    "metrics": ["localize", "write"],
    "admin": ["localize", "write"],
    "read": [],
}


def _required_scope(path: str, dependant) -> str:
    scopes = set()
    stack = list(dependant.dependencies)
    while stack:
        dep = stack.pop()
        scope = getattr(dep.call, "required_scope", None)
        if scope is not None:
            scopes.add(scope)
        stack.extend(dep.dependencies)
    assert len(scopes) == 1, f"{path} must require exactly one scope, found {scopes}"
    return scopes.pop()


def _flat_routes(app):
    """(path, route, dependant, methods) of every route; FastAPI >= 0.16x keeps included
    routers as lazy contexts in app.routes, older versions as plain routes."""
    for route in app.routes:
        contexts = getattr(route, "effective_route_contexts", None)
        if contexts is None:
            yield (
                route.path,
                route,
                getattr(route, "dependant", None),
                getattr(route, "methods", None),
            )
            continue
        for ctx in contexts():
            original = ctx.original_route
            yield (
                ctx.path or original.path,
                original,
                ctx.dependant or original.dependant,
                ctx.methods or getattr(original, "methods", None),
            )


def _routes(app):
    for path, route, dependant, methods in _flat_routes(app):
        if path in EXEMPT:
            continue
        assert isinstance(route, APIRoute | APIWebSocketRoute), path
        concrete = re.sub(r"\{[^}]+\}", "999999", path)  # ids that do not exist
        for method in sorted(methods) if isinstance(route, APIRoute) else ["WS"]:
            yield method, concrete, _required_scope(path, dependant)


def _status(client: TestClient, method: str, path: str, headers: dict) -> int:
    if method == "WS":
        try:
            with client.websocket_connect(path, headers=headers):
                return 101
        except WebSocketDenialResponse as denial:
            return denial.status_code
    # streamed: the status line, not the body (an event stream of a map the key may read
    # stays open until its idle timeout)
    with client.stream(method, path, headers=headers) as response:
        return response.status_code


def test_every_route_checks_its_scope(fresh):
    client, keys = fresh
    checked = 0
    for method, path, scope in _routes(client.app):
        for headers in ({}, {"X-API-Key": "mlk_" + "x" * 43}, {"Authorization": "Bearer nope"}):
            assert _status(client, method, path, headers) == 401, (method, path, headers)
        for wrong in WRONG_KEYS[scope]:
            assert _status(client, method, path, keys.header(wrong)) == 403, (method, path, wrong)
        right = {
            "admin": {"admin"},
            "metrics": {"admin"},
            "localize": {"localize"},
            "read": {"localize", "write"},
        }
        for key in right.get(scope, {"write"}) | {"admin"}:
            status = _status(client, method, path, keys.header(key))
            assert status not in (401, 403), (method, path, key, status)
        checked += 1
    assert checked >= 25  # every resource is in the matrix


def test_exempt_routes_need_no_key(fresh):
    client, _ = fresh
    for path in ("/healthz", "/readyz", "/openapi.json", "/docs"):
        assert client.get(path).status_code == 200, path


def test_bearer_header_and_websocket_query_key_are_accepted(fresh):
    client, keys = fresh
    bearer = {"Authorization": f"Bearer {keys.localize}"}
    assert client.get("/v1/maps", headers=bearer).status_code == 200
    # The map does not exist: the key passed, the map check answers 404.
    with pytest.raises(WebSocketDenialResponse) as denial:
        with client.websocket_connect(f"/v1/maps/999999/stream?key={keys.localize}"):
            pass
    assert denial.value.status_code == 404


def test_revoked_key_is_refused(fresh):
    client, keys = fresh
    listed = client.get("/v1/keys", headers=keys.header("admin")).json()["items"]
    (car,) = [k for k in listed if k["name"] == "localize"]
    assert "key" not in car and car["prefix"] == keys.localize[:12]
    assert client.delete(f"/v1/keys/{car['id']}", headers=keys.header("admin")).status_code == 200
    assert client.get("/v1/maps", headers=keys.header("localize")).status_code == 401


def test_metrics_can_be_made_public(tmp_path):
    with open_client(make_settings(tmp_path / "d", metrics_public=True)) as client:
        assert client.get("/metrics").status_code == 200
    with open_client(make_settings(tmp_path / "e")) as client:
        assert client.get("/metrics").status_code == 401
        assert client.get("/metrics", headers={"X-API-Key": ADMIN_KEY}).status_code == 200


def test_a_metrics_key_scrapes_metrics_and_nothing_an_admin_does(fresh):
    client, keys = fresh
    admin = keys.header("admin")
    made = client.post(
        "/v1/keys", json={"name": "prometheus", "scopes": ["metrics"]}, headers=admin
    )
    assert made.status_code == 201, made.text
    scraper = {"X-API-Key": made.json()["key"]}
    scraped = client.get("/metrics", headers=scraper)
    assert scraped.status_code == 200
    assert scraped.headers["content-type"].startswith("text/plain")
    assert "# TYPE monoloc_http_request_duration_seconds histogram" in scraped.text
    assert client.get("/v1/keys", headers=scraper).status_code == 403
    assert client.post("/v1/maps", json={"name": "x"}, headers=scraper).status_code == 403
    assert client.get("/metrics", headers=keys.header("localize")).status_code == 403


def test_bootstrap_key_is_used_only_on_an_empty_key_table(tmp_path):
    from monoloc.server.storage.db import create_engine_for, make_session_factory, session_scope
    from monoloc.server.storage.keys import list_api_keys

    settings = make_settings(tmp_path / "d")
    for _ in range(2):
        with open_client(settings) as client:
            assert client.get("/v1/keys", headers={"X-API-Key": ADMIN_KEY}).status_code == 200
    engine = create_engine_for(settings)
    with session_scope(make_session_factory(engine)) as session:
        assert [k.name for k in list_api_keys(session)] == ["bootstrap"]
    engine.dispose()
    with pytest.raises(Exception, match="MONOLOC_BOOTSTRAP_ADMIN_KEY"):
        with open_client(make_settings(tmp_path / "bad", bootstrap_admin_key="short")):
            pass


def test_every_key_reads_the_maps_and_its_own_record(fresh):
    """Vehicles and mapping teams both see what a map looks like; GET /v1/keys/me tells a
    key (the console) its own scopes."""
    client, keys = fresh
    for which, scopes in (("localize", ["localize"]), ("write", ["map:write"])):
        headers = keys.header(which)
        assert client.get("/v1/maps", headers=headers).status_code == 200
        me = client.get("/v1/keys/me", headers=headers).json()
        assert me["scopes"] == scopes and me["prefix"] == getattr(keys, which)[:12]
        assert "key" not in me
    assert client.get("/v1/keys/me", headers=keys.header("admin")).json()["scopes"] == ["admin"]
    # reading is not writing: a vehicle key still may not edit, nor a write key localize
    assert client.post("/v1/maps/1/runs", headers=keys.header("localize")).status_code == 403
    answer = client.post("/v1/maps/1/localize", headers=keys.header("write"))
    assert answer.status_code == 403


def test_a_replica_asks_the_database_about_a_key_once_per_key_cache_time(tmp_path):
    """A vehicle's frames do not each cost a database query for its key; a key revoked
    by another process (another replica, `monoloc keys revoke`) is refused once this
    replica's memory of it expires, and one revoked through this replica at once."""
    import time

    from sqlalchemy import event

    from monoloc.server.storage.db import session_scope
    from monoloc.server.storage.keys import revoke_api_key

    # a cache long enough for five requests on a loaded machine, short enough to wait out
    with open_client(make_settings(tmp_path / "d", key_cache_s=3.0)) as client:
        keys = create_keys(client)
        state = client.app.state.monoloc
        key_queries = []

        def count(conn, cursor, statement, *args):
            if "FROM api_keys" in statement:
                key_queries.append(statement)

        event.listen(state.engine, "before_cursor_execute", count)
        for _ in range(5):
            assert client.get("/v1/maps", headers=keys.header("localize")).status_code == 200
        assert len(key_queries) == 1
        listed = client.get("/v1/keys", headers=keys.header("admin")).json()["items"]
        (car,) = [k for k in listed if k["name"] == "localize"]
        (team,) = [k for k in listed if k["name"] == "write"]
        with session_scope(state.sessions) as session:  # another process revokes it
            revoke_api_key(session, car["id"])
        deadline = time.monotonic() + 60.0
        while client.get("/v1/maps", headers=keys.header("localize")).status_code == 200:
            assert time.monotonic() < deadline, "a key revoked elsewhere was never refused"
            time.sleep(0.1)
        assert client.get("/v1/maps", headers=keys.header("write")).status_code == 200
        assert (
            client.delete(f"/v1/keys/{team['id']}", headers=keys.header("admin")).status_code == 200
        )
        assert client.get("/v1/maps", headers=keys.header("write")).status_code == 401


def test_the_key_cache_can_be_turned_off(tmp_path):
    from sqlalchemy import event

    with open_client(make_settings(tmp_path / "d", key_cache_s=0)) as client:
        keys = create_keys(client)
        key_queries = []
        event.listen(
            client.app.state.monoloc.engine,
            "before_cursor_execute",
            lambda conn, cursor, statement, *a: (
                key_queries.append(statement) if "FROM api_keys" in statement else None
            ),
        )
        for _ in range(3):
            assert client.get("/v1/maps", headers=keys.header("localize")).status_code == 200
        assert len(key_queries) == 3


CAMERA = dict(fx=700.0, fy=700.0, cx=620.0, cy=188.0, width_px=1241, height_px=376)


def _admin_key_ids(client, keys) -> list[int]:
    listed = client.get("/v1/keys", headers=keys.header("admin")).json()["items"]
    return [k["id"] for k in listed if "admin" in k["scopes"] and k["revoked_at"] is None]


def test_the_last_active_admin_key_cannot_be_revoked(fresh):
    client, keys = fresh
    (bootstrap,) = _admin_key_ids(client, keys)
    refused = client.delete(f"/v1/keys/{bootstrap}", headers=keys.header("admin"))
    assert refused.status_code == 409, refused.text
    assert "last active admin key" in refused.json()["error"]["message"]
    assert client.get("/v1/keys", headers=keys.header("admin")).status_code == 200
    made = client.post(
        "/v1/keys", json={"name": "ops", "scopes": ["admin"]}, headers=keys.header("admin")
    )
    ops = {"X-API-Key": made.json()["key"]}
    assert client.delete(f"/v1/keys/{bootstrap}", headers=ops).status_code == 200
    assert client.get("/v1/keys", headers=keys.header("admin")).status_code == 401
    again = client.delete(f"/v1/keys/{made.json()['id']}", headers=ops)
    assert again.status_code == 409 and client.get("/v1/keys", headers=ops).status_code == 200


def _two_maps_and_a_tenant(client, keys) -> tuple[int, int, dict]:
    ids = []
    for name in ("ours", "theirs"):
        r = client.post(
            "/v1/maps", json={"name": name, "camera": CAMERA}, headers=keys.header("admin")
        )
        assert r.status_code == 201, r.text
        ids.append(r.json()["id"])
    ours, theirs = ids
    made = client.post(
        "/v1/keys",
        json={"name": "tenant", "scopes": ["localize", "map:write"], "maps": [ours]},
        headers=keys.header("admin"),
    )
    assert made.status_code == 201, made.text
    assert made.json()["maps"] == [ours]
    return ours, theirs, {"X-API-Key": made.json()["key"]}


def test_a_key_limited_to_maps_is_refused_every_other_map_on_every_route(fresh):
    """Every route, the stream and the console's routes with a {map_id}: another map is
    403 for the tenant's key; its own map passes the map check."""
    client, keys = fresh
    ours, theirs, tenant = _two_maps_and_a_tenant(client, keys)
    checked = 0
    for path, route, dependant, methods in _flat_routes(client.app):
        if "{map_id}" not in path or path in EXEMPT:
            continue
        scope = _required_scope(path, dependant)
        for method in sorted(methods) if isinstance(route, APIRoute) else ["WS"]:
            for map_id, allowed in ((theirs, False), (ours, True)):
                concrete = re.sub(r"\{[^}]+\}", "999999", path.replace("{map_id}", str(map_id)))
                status = _status(client, method, concrete, tenant)
                if not allowed:
                    assert status == 403, (method, concrete, status)
                elif scope != "admin":
                    assert status != 403, (method, concrete, status)
            checked += 1
    assert checked >= 20
    me = client.get("/v1/keys/me", headers=tenant).json()
    assert me["maps"] == [ours]
    listed = client.get("/v1/maps", headers=tenant).json()["items"]
    assert [m["id"] for m in listed] == [ours]
    assert len(client.get("/v1/maps", headers=keys.header("localize")).json()["items"]) == 2


def test_a_key_limited_to_maps_sees_only_their_jobs(fresh):
    client, keys = fresh
    ours, theirs, tenant = _two_maps_and_a_tenant(client, keys)
    job_ids = {}
    for map_id in (ours, theirs):
        r = client.post(
            f"/v1/maps/{map_id}/vocabulary/jobs",
            json={"vocabulary": "default"},
            headers=keys.header("admin"),
        )
        assert r.status_code in (201, 202), r.text
        job_ids[map_id] = r.json()["id"]
    listed = client.get("/v1/jobs", headers=tenant).json()["items"]
    assert {j["map_id"] for j in listed} == {ours}
    assert client.get(f"/v1/jobs?map_id={theirs}", headers=tenant).status_code == 403
    for suffix, method in (("", "GET"), ("/resume", "POST"), ("/cancel", "POST")):
        path = f"/v1/jobs/{job_ids[theirs]}{suffix}"
        assert client.request(method, path, headers=tenant).status_code == 403, path
    assert client.get(f"/v1/jobs/{job_ids[ours]}", headers=tenant).status_code == 200


def test_map_limits_are_checked_at_creation(fresh):
    client, keys = fresh
    ours, _, _ = _two_maps_and_a_tenant(client, keys)
    admin = keys.header("admin")
    for body in (
        {"name": "x", "scopes": ["admin"], "maps": [ours]},
        {"name": "x", "scopes": ["localize"], "maps": [999999]},
        {"name": "x", "scopes": ["localize"], "maps": []},
    ):
        r = client.post("/v1/keys", json=body, headers=admin)
        assert r.status_code == 422, (body, r.text)
    plain = client.post("/v1/keys", json={"name": "all", "scopes": ["localize"]}, headers=admin)
    assert plain.json()["maps"] is None

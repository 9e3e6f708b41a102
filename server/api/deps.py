"""Dependencies of the routes: the app's state, a database session, the map registry,
the settings, CPU offloading, and API-key checks by scope.

API keys (documented in the OpenAPI security schemes):

* HTTP: header ``X-API-Key: mlk_...``, or ``Authorization: Bearer mlk_...``.
* WebSocket: the same headers, or the query parameter ``?key=mlk_...`` (browsers cannot
  set headers on a WebSocket; prefer headers elsewhere: URLs end up in logs).

No key, or an unknown/revoked one: 401. A valid key without the route's scope: 403. A
key limited to some maps (``ApiKeyRecord.maps``) asking for another map by the path's
``{map_id}``: 403 (lists and jobs are filtered by the routes themselves).
``admin`` grants every scope. Exempt (no key): ``/healthz``, ``/readyz``, ``/docs``,
``/redoc`` and ``/openapi.json`` (the API description holds no data), and ``/metrics``
only when ``MONOLOC_METRICS_PUBLIC=true`` (otherwise it needs ``admin``).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Annotated, Any, TypeVar

import numpy as np
from fastapi import Depends, Security
from fastapi.security import APIKeyHeader, APIKeyQuery, HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker
from starlette.requests import HTTPConnection

from monoloc.server.api.admission import Admission
from monoloc.server.api.camera_cache import CameraCache
from monoloc.server.api.errors import ForbiddenError, NotReadyError, UnauthorizedError
from monoloc.server.api.key_cache import DATABASE_UNREACHABLE, KeyCache
from monoloc.server.api.metrics import Metrics
from monoloc.server.jobs.runner import JobRunner
from monoloc.server.map_registry import MapRegistry
from monoloc.server.settings import Settings
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.keys import verify_api_key
from monoloc.server.storage.records import READ_ACCESS, ApiKeyRecord

T = TypeVar("T")


@dataclass
class AppState:
    """Everything a request may need, built by the lifespan (``app.state.monoloc``)."""

    settings: Settings
    engine: Engine
    sessions: sessionmaker[Session]
    registry: MapRegistry
    jobs: JobRunner
    metrics: Metrics
    seeds: np.random.SeedSequence
    admission: Admission
    keys: KeyCache = field(default_factory=lambda: KeyCache(0.0))
    cameras: CameraCache = field(default_factory=lambda: CameraCache(0.0))
    ready: bool = False
    _seed_lock: threading.Lock = field(default_factory=threading.Lock)

    def next_seed(self) -> int:
        """A fresh 63-bit seed from the server's seed sequence (thread-safe)."""
        with self._seed_lock:
            child = self.seeds.spawn(1)[0]
        return int(child.generate_state(2, np.uint64)[0] >> np.uint64(1))

    async def run_cpu(self, fn: Callable[..., T], *args: Any) -> T:
        """Run CPU work (decode, ORB, PnP, entry building) on the request's admission lane
        (dropped first if its deadline passed or its client left)."""
        return await self.admission.run(fn, *args)


def get_state(conn: HTTPConnection) -> AppState:
    state = getattr(conn.app.state, "monoloc", None)
    if state is None or not state.ready:
        raise NotReadyError("the server is starting or stopping; retry shortly")
    return state


StateDep = Annotated[AppState, Depends(get_state)]


def get_settings_dep(state: StateDep) -> Settings:
    return state.settings


def get_registry(state: StateDep) -> MapRegistry:
    return state.registry


def get_session(state: StateDep) -> Iterator[Session]:
    """A session for one request; handlers commit explicitly (uncommitted work rolls back)."""
    session = state.sessions()
    try:
        yield session
    finally:
        session.close()


SettingsDep = Annotated[Settings, Depends(get_settings_dep)]
RegistryDep = Annotated[MapRegistry, Depends(get_registry)]
SessionDep = Annotated[Session, Depends(get_session)]

_header_scheme = APIKeyHeader(
    name="X-API-Key", auto_error=False, description="An API key, e.g. `mlk_...`."
)
_bearer_scheme = HTTPBearer(auto_error=False, description="The API key as a bearer token.")
_query_scheme = APIKeyQuery(
    name="key", auto_error=False, description="WebSocket only: the API key as ?key=..."
)


# Where GuardedRoute (server/api/guard.py) leaves the key record it checked before the body.
KEY_RECORD_SCOPE = "monoloc.api_key"


def presented_key(conn: HTTPConnection) -> str | None:
    """The key of an HTTP request's headers: ``X-API-Key``, else ``Authorization: Bearer``."""
    header = conn.headers.get("x-api-key")
    if header:
        return header
    scheme, _, credentials = conn.headers.get("authorization", "").partition(" ")
    return credentials.strip() or None if scheme.lower() == "bearer" else None


def path_map_id(conn: HTTPConnection) -> int | None:
    """The ``{map_id}`` of the request's path, if it has one that is a number."""
    value = str(conn.scope.get("path_params", {}).get("map_id", ""))
    return int(value) if value.isdigit() else None


def check_map_access(record: ApiKeyRecord, map_id: int | None) -> None:
    """403 if ``record`` is limited to maps that do not include ``map_id``."""
    if map_id is not None and not record.can_see_map(map_id):
        raise ForbiddenError(
            f"this API key ({record.prefix}...) is limited to maps {sorted(record.maps or ())}"
            f" and may not touch map {map_id}"
        )


def authenticate(
    state: AppState, presented: str | None, scope: str, map_id: int | None = None
) -> ApiKeyRecord:
    """The key record if ``presented`` is a valid key with ``scope`` that may touch
    ``map_id`` (when given); 401/403 otherwise."""
    if not presented:
        raise UnauthorizedError(
            "missing API key: send it in the X-API-Key header (or Authorization: Bearer)"
        )
    record = state.keys.get(presented)
    if record is None:
        try:
            with session_scope(state.sessions) as session:
                record = verify_api_key(session, presented)
        except DATABASE_UNREACHABLE:
            record = state.keys.get_stale(presented)
            if record is None:
                raise
        else:
            if record is None:
                raise UnauthorizedError("unknown or revoked API key")
            state.keys.put(presented, record)
    if not record.has_scope(scope):
        raise ForbiddenError(
            f"this API key ({record.prefix}..., scopes {sorted(record.scopes)}) lacks the "
            f"'{scope}' scope this route needs"
        )
    check_map_access(record, map_id)
    return record


def require_scope(scope: str, *, websocket: bool = False) -> Callable[..., ApiKeyRecord]:
    """A dependency admitting keys with ``scope`` (``websocket`` also reads ``?key=``)."""

    def http_dependency(
        conn: HTTPConnection,
        state: StateDep,
        header_key: Annotated[str | None, Security(_header_scheme)] = None,
        bearer: Annotated[HTTPAuthorizationCredentials | None, Security(_bearer_scheme)] = None,
    ) -> ApiKeyRecord:
        checked = conn.scope.get(KEY_RECORD_SCOPE)
        map_id = path_map_id(conn)
        if isinstance(checked, ApiKeyRecord) and checked.has_scope(scope):
            check_map_access(checked, map_id)
            return checked  # checked before the body was read (GuardedRoute)
        presented = header_key or (bearer.credentials if bearer else None)
        return authenticate(state, presented, scope, map_id)

    def ws_dependency(
        conn: HTTPConnection,
        state: StateDep,
        header_key: Annotated[str | None, Security(_header_scheme)] = None,
        bearer: Annotated[HTTPAuthorizationCredentials | None, Security(_bearer_scheme)] = None,
        query_key: Annotated[str | None, Security(_query_scheme)] = None,
    ) -> ApiKeyRecord:
        presented = header_key or (bearer.credentials if bearer else None) or query_key
        return authenticate(state, presented, scope, path_map_id(conn))

    dependency = ws_dependency if websocket else http_dependency
    dependency.__name__ = f"require_{scope.replace(':', '_')}"
    dependency.required_scope = scope  # read by the scope-matrix test and the docs
    return dependency


LocalizeKey = Annotated[ApiKeyRecord, Depends(require_scope("localize"))]
# Any valid key: vehicles and mapping teams both see the maps (the console's read pages).
ReadKey = Annotated[ApiKeyRecord, Depends(require_scope(READ_ACCESS))]
MapWriteKey = Annotated[ApiKeyRecord, Depends(require_scope("map:write"))]
AdminKey = Annotated[ApiKeyRecord, Depends(require_scope("admin"))]
StreamKey = Annotated[ApiKeyRecord, Depends(require_scope("localize", websocket=True))]

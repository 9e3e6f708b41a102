"""``/healthz`` (the process answers) and ``/readyz`` (database reachable, maps loaded);
neither needs a key."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse
from sqlalchemy import text

from monoloc.server.api.deps import AppState
from monoloc.server.api.schemas_admin import HealthStatus

router = APIRouter(tags=["health"])


@router.get(
    "/healthz",
    response_model=HealthStatus,
    response_model_exclude_none=True,
    summary="Liveness (no key needed)",
)
def healthz() -> HealthStatus:
    """200 while the process serves requests."""
    return HealthStatus(status="ok")


@router.get(
    "/readyz",
    response_model=HealthStatus,
    responses={
        503: {
            "model": HealthStatus,
            "content": {"application/json": {"example": {"status": "starting"}}},
        }
    },
    summary="Readiness (no key needed)",
)
def readyz(request: Request):
    """200 once the database is migrated and reachable and every map's index is loaded;
    503 while starting or stopping."""
    state: AppState | None = getattr(request.app.state, "monoloc", None)
    if state is None or not state.ready:
        return JSONResponse({"status": "starting"}, status_code=503)
    try:
        with state.engine.connect() as connection:
            connection.execute(text("SELECT 1"))
    except Exception:
        return JSONResponse({"status": "database unreachable"}, status_code=503)
    return HealthStatus(status="ready", maps_loaded=len(state.registry.loaded()))

"""One router per resource, all under /v1 (health and metrics at the root)."""

from __future__ import annotations

from monoloc.server.api.routes import (
    calibration,
    cameras,
    entries,
    geo,
    health,
    jobs,
    keys,
    localize,
    maps,
    replica,
    runs,
    stream,
)

ROUTERS = [
    maps.router,
    replica.router,
    runs.router,
    jobs.router,
    entries.router,
    localize.router,
    stream.router,
    calibration.router,
    geo.router,
    keys.router,
    cameras.router,
    health.router,
]

"""The FastAPI application: ``create_app(settings)`` builds it; its lifespan does the work.

Start-up (in order): data directories; Alembic upgrade of the database and the bootstrap
admin key (if configured and no key exists), both under the database's start-up lock so
replicas starting together take turns; thread counts (OpenCV ``cv_threads``, FAISS
``faiss_threads``, BLAS 1 thread: on 2 cores an oversubscribed OpenBLAS makes small
mat-vecs many times slower); every map's index loaded (or rebuilt) by the registry and
its replica sync started; the job runner (leases: it takes over jobs whose holder died).
Shutdown: sync stopped, running jobs handed back to the queue, indexes persisted, the
engine disposed. Any number of processes may serve one database: each is a replica
(``server/map_registry.py``), admission control bounds what each one accepts
(``server/api/admission.py``).
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from pathlib import Path

import anyio
import numpy as np
from fastapi import FastAPI

from monoloc.server.api.admission import Admission, LaneConfig, install_admission
from monoloc.server.api.console import install_console
from monoloc.server.api.deps import AppState
from monoloc.server.api.errors import install_error_handlers
from monoloc.server.api.guard import document_body_limits
from monoloc.server.api.limits import BodySizeLimitMiddleware
from monoloc.server.api.metrics import GaugeRefresher, Metrics, RequestMetricsMiddleware
from monoloc.server.api.openapi_links import document_links
from monoloc.server.api.openapi_rules import document_cross_field_rules
from monoloc.server.settings import Settings, get_settings
from monoloc.server.threads import limit_threads

log = logging.getLogger(__name__)

API_DESCRIPTION = """
Visual localization against a map of geo-tagged reference images.

**Authentication.** Every route but `/healthz`, `/readyz` and these docs needs an API
key: header `X-API-Key: mlk_...` (or `Authorization: Bearer mlk_...`; the WebSocket
stream also takes `?key=`). Scopes: `localize` (vehicles), `map:write` (uploads,
entries, calibration), `admin` (maps, keys, `/metrics`; implies every scope). Reading
what a map looks like (maps, calibration, geo reference, poses, coverage, live vehicles,
`GET /v1/keys/me`) takes a valid key of any scope. No key:
401; wrong scope: 403. `/metrics` takes a `metrics` key (a scraper's) or an admin key,
or none with `MONOLOC_METRICS_PUBLIC=true`.
Create keys with `monoloc keys create --scope ... --name ...` (same data directory), or
start the server with `MONOLOC_BOOTSTRAP_ADMIN_KEY` while no key exists yet.

**Randomness.** RANSAC in `localize` uses a per-request generator seeded by the
request's `seed` field, else by a fresh draw from the server's seed sequence
(`MONOLOC_LOCALIZE_SEED`); the answer reports the seed, so any answer can be repeated.

**Errors** are JSON: `{"error": {"code": "...", "message": "..."}}`.

**Frames.** Poses are in the z-up world (metres, radians); `T_world_from_cam` is 16
numbers, row-major.

**Stream** (WebSocket, not listed below): `/v1/maps/{map_id}/stream`, `localize` scope
(header, or `?key=` for browsers). Send binary messages: 4-byte big-endian header length,
a UTF-8 JSON header `{"seq": 17, "t": 1.7, "prior": {"x_m": .., "y_m": .., "radius_m":
.., "yaw_rad": .., "yaw_tolerance_rad": ..}, "k": 10}` (prior, k optional), then the
PNG/JPEG bytes. One JSON answer per frame, in order: the localize answer plus `seq` and
`t`, or `{"seq": 18, "dropped": true, "reason": "stale"}` when the server fell behind
(at most `MONOLOC_STREAM_MAX_PENDING_FRAMES` frames wait; the oldest is dropped), or
`{"seq": 19, "error": {...}}`.
"""

TAGS = [
    {"name": "maps", "description": "Maps: camera, vocabulary, version, counts (admin)."},
    {"name": "runs", "description": "Upload a KITTI or TUM recording; ingestion is a job."},
    {"name": "jobs", "description": "Durable jobs: state, progress, resume."},
    {"name": "entries", "description": "Reference images of a map (operators)."},
    {"name": "localize", "description": "Pose hypotheses for a query frame."},
    {"name": "stream", "description": "WebSocket stream of frames per vehicle."},
    {
        "name": "calibration",
        "description": "Measurement-model parameters per map, and per condition (an entry "
        "tag such as night) calibrated on a run recorded in it.",
    },
    {"name": "keys", "description": "API keys (admin)."},
    {"name": "health", "description": "Liveness, readiness, Prometheus metrics."},
]


def admission_for(settings: Settings, metrics: Metrics) -> Admission:
    """The lanes of admission control, sized by the settings."""
    return Admission(
        {
            "localize": LaneConfig(
                settings.worker_threads,
                settings.localize_queue_depth,
                settings.localize_deadline_ms,
            ),
            "write": LaneConfig(
                settings.write_threads, settings.write_queue_depth, settings.write_deadline_ms
            ),
            # Uploads spool to disk and hand work to the job runner; the deadline only
            # bounds the wait for a slot, the stall timeout the upload.
            "jobs": LaneConfig(1, settings.job_queue_depth, 3_600_000, body_by_deadline=False),
            "read": LaneConfig(
                settings.read_threads, settings.read_queue_depth, settings.read_deadline_ms
            ),
        },
        metrics,
        body_stall_s=settings.body_stall_timeout_s,
    )


def _start(settings: Settings, metrics: Metrics, admission: Admission) -> AppState:
    """Blocking start-up work (run in a thread by the lifespan)."""
    from monoloc.server.api.bootstrap import clean_incoming_uploads, prepare_database
    from monoloc.server.api.camera_cache import CameraCache
    from monoloc.server.api.key_cache import KeyCache
    from monoloc.server.index.warmup import warm_up as warm_up_index
    from monoloc.server.jobs.handlers import HANDLERS
    from monoloc.server.jobs.runner import JobRunner
    from monoloc.server.map_registry import MapRegistry
    from monoloc.server.storage.db import make_session_factory
    from monoloc.server.vision.warmup import warm_up as warm_up_vision

    # Compile or load the numba kernels now, not in the first request.
    warm_up_vision()
    warm_up_index()
    Path(settings.data_dir).mkdir(parents=True, exist_ok=True)
    clean_incoming_uploads(settings)
    engine = prepare_database(settings)
    sessions = make_session_factory(engine)
    assert settings.index_dir is not None
    registry = MapRegistry(sessions, Path(settings.index_dir))
    n_maps = registry.load_all()
    log.info("loaded %d map(s)", n_maps)
    postgres = engine.dialect.name == "postgresql"
    registry.start_sync(settings.replica_sync_s, settings.database_url if postgres else None)
    runner = JobRunner(sessions, registry, settings, HANDLERS)
    runner.start()
    return AppState(
        settings=settings,
        engine=engine,
        sessions=sessions,
        registry=registry,
        jobs=runner,
        metrics=metrics,
        admission=admission,
        keys=KeyCache(settings.key_cache_s),
        cameras=CameraCache(settings.key_cache_s),
        seeds=np.random.SeedSequence(settings.localize_seed),
    )


def _stop(state: AppState) -> None:
    state.admission.stop()
    state.registry.stop_sync()
    state.jobs.stop()
    try:
        state.registry.persist()
    finally:
        state.engine.dispose()


def _document_limits(app: FastAPI, settings: Settings) -> None:
    """The OpenAPI description names each route's body limit in bytes (server/api/guard.py),
    the cross-field rules (server/api/openapi_rules.py) and the links between operations
    (server/api/openapi_links.py)."""
    build = app.openapi

    def openapi() -> dict:
        if app.openapi_schema is None:
            spec = document_cross_field_rules(document_body_limits(build(), settings))
            app.openapi_schema = document_links(spec)
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


def create_app(settings: Settings | None = None) -> FastAPI:
    """The API for ``settings`` (default: read from the environment now)."""
    settings = settings or get_settings()
    metrics = Metrics()
    admission = admission_for(settings, metrics)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        from monoloc.server.api.redact import install_log_redaction

        install_log_redaction()
        limiter = limit_threads(settings)
        state = await anyio.to_thread.run_sync(_start, settings, metrics, admission)
        gauges = GaugeRefresher(
            lambda: metrics.set_process_gauges(admission.gauges(), len(state.registry.loaded()))
        )
        gauges.start()
        relay = _board_relay(app, state)
        state.ready = True
        app.state.monoloc = state
        try:
            yield
        finally:
            state.ready = False
            gauges.stop()
            if relay is not None:
                relay.stop()
            await anyio.to_thread.run_sync(_stop, state)
            limiter.restore_original_limits()

    from monoloc.server.api.routes import ROUTERS
    from monoloc.server.api.routes.metrics import metrics_router

    app = FastAPI(
        title="monoloc map server",
        version="1",
        description=API_DESCRIPTION,
        openapi_tags=TAGS,
        lifespan=lifespan,
        docs_url=None,  # /docs and /redoc from packaged assets: install_console
        redoc_url=None,
        form_limits={"max_files": settings.max_archive_members, "max_fields": 1000},
    )
    install_error_handlers(app)
    for router in ROUTERS:
        app.include_router(router)
    app.include_router(metrics_router(settings.metrics_public))
    _document_limits(app, settings)
    install_console(app)  # /ui, offline /docs and /redoc, the console's JSON routes
    app.add_middleware(BodySizeLimitMiddleware, max_body_bytes=settings.max_body_bytes)
    install_admission(app, admission)  # inside the metrics: shed requests are timed too
    app.add_middleware(RequestMetricsMiddleware, metrics=metrics, known_map=_known_map(app))
    return app


def _board_relay(app: FastAPI, state: AppState):
    """On PostgreSQL, the live-vehicle board shared with the other replicas (started)."""
    if state.engine.dialect.name != "postgresql":
        return None
    from monoloc.server.api.console.live import vehicle_board
    from monoloc.server.api.console.relay import BoardRelay

    relay = BoardRelay(vehicle_board(app), state.settings.database_url)
    relay.start()
    return relay


def _known_map(app: FastAPI) -> Callable[[int], bool]:
    """Whether ``map_id`` is loaded in ``app``'s registry (a metric label of real maps)."""

    def known(map_id: int) -> bool:
        state = getattr(app.state, "monoloc", None)
        return state is not None and map_id in state.registry.loaded()

    return known


def create_app_from_env() -> FastAPI:
    """Factory for ``uvicorn --factory monoloc.server.api.app:create_app_from_env``."""
    return create_app(get_settings())

"""``/metrics``: Prometheus text through prometheus_client (server/api/metrics.py), for a
key with the ``metrics`` scope (or ``admin``), or anyone when ``MONOLOC_METRICS_PUBLIC``."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Response
from sqlalchemy import func, select

from monoloc.server.api.convert import AUTH_ERRORS
from monoloc.server.api.deps import AppState, StateDep, require_scope
from monoloc.server.api.metrics import CONTENT_TYPE, ScrapeGauges
from monoloc.server.storage.models import Entry, Job, Map


def _database_gauges(state: AppState) -> ScrapeGauges:
    """The gauges every replica reads alike from the database, at scrape time."""
    with state.sessions() as session:
        per_map = session.execute(
            select(Map.id, Map.name, func.count(Entry.id))
            .outerjoin(Entry, Entry.map_id == Map.id)
            .group_by(Map.id, Map.name)
        ).all()
        jobs = session.execute(
            select(Job.kind, Job.state, func.count(Job.id)).group_by(Job.kind, Job.state)
        ).all()
    return ScrapeGauges(
        [
            (
                "monoloc_map_entries",
                "Entries per map.",
                ("map_id", "map"),
                {(str(i), name): n for i, name, n in per_map},
            ),
            (
                "monoloc_jobs",
                "Jobs by kind and state.",
                ("kind", "state"),
                {(kind, st): n for kind, st, n in jobs},
            ),
        ]
    )


def refresh_process_gauges(state: AppState) -> None:
    """This process's admission lanes and loaded maps into its gauges."""
    state.metrics.set_process_gauges(state.admission.gauges(), len(state.registry.loaded()))


def _metrics_response(state: AppState) -> Response:
    refresh_process_gauges(state)
    body = state.metrics.exposition(_database_gauges(state))
    return Response(body, media_type=CONTENT_TYPE)


def metrics_router(public: bool) -> APIRouter:
    """The /metrics route, open or behind a ``metrics`` (or ``admin``) key."""
    metrics = APIRouter(tags=["health"])
    description = "Prometheus text exposition: request latency histograms per route, "
    description += "localize stage timings, frames per map by outcome, stream frames, "
    description += "admission lanes, entries per map, jobs by state. Under "
    description += "`monoloc serve --workers N` every worker process's values, summed."
    responses = {
        200: {
            "content": {
                "text/plain": {
                    "example": (
                        'monoloc_localize_frames_total{map_id="1",outcome="hypotheses"} 3860.0\n'
                    )
                }
            }
        }
    }
    if public:

        @metrics.get(
            "/metrics",
            response_class=Response,
            responses=responses,
            summary="Prometheus metrics",
            description=description,
        )
        def open_metrics(state: StateDep) -> Response:
            return _metrics_response(state)
    else:

        @metrics.get(
            "/metrics",
            response_class=Response,
            responses={**responses, **AUTH_ERRORS},
            summary="Prometheus metrics",
            description=description + " Needs a key with the `metrics` scope (or `admin`).",
            dependencies=[Depends(require_scope("metrics"))],
        )
        def scoped_metrics(state: StateDep) -> Response:
            return _metrics_response(state)

    return metrics

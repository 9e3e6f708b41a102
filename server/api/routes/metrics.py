"""``/metrics``: Prometheus text (admin key unless ``MONOLOC_METRICS_PUBLIC=true``)."""

from __future__ import annotations

from fastapi import APIRouter, Depends
from fastapi.responses import PlainTextResponse
from sqlalchemy import func, select

from monoloc.server.api.convert import AUTH_ERRORS
from monoloc.server.api.deps import AppState, StateDep, require_scope
from monoloc.server.api.metrics import render_gauge
from monoloc.server.storage.models import Entry, Job, Map


def _scrape(state: AppState) -> str:
    lines: list[str] = []
    lines.extend(state.metrics.requests.render())
    lines.extend(state.metrics.localize_stages.render())
    lines.extend(state.metrics.stream_frames.render())
    lines.extend(state.metrics.admission_shed.render())
    lines.extend(state.metrics.admission_expired.render())
    for kind, values in state.admission.gauges().items():
        lines.extend(
            render_gauge(
                f"monoloc_admission_{kind}",
                f"Requests per admission lane: {kind}.",
                ("lane",),
                values,
            )
        )
    with state.sessions() as session:
        per_map = session.execute(
            select(Map.id, Map.name, func.count(Entry.id))
            .outerjoin(Entry, Entry.map_id == Map.id)
            .group_by(Map.id, Map.name)
        ).all()
        jobs = session.execute(
            select(Job.kind, Job.state, func.count(Job.id)).group_by(Job.kind, Job.state)
        ).all()
    lines.extend(
        render_gauge(
            "monoloc_map_entries",
            "Entries per map.",
            ("map_id", "map"),
            {(str(i), name): n for i, name, n in per_map},
        )
    )
    lines.extend(
        render_gauge(
            "monoloc_jobs",
            "Jobs by kind and state.",
            ("kind", "state"),
            {(kind, st): n for kind, st, n in jobs},
        )
    )
    lines.extend(
        render_gauge(
            "monoloc_maps_loaded",
            "Maps whose index is in memory.",
            (),
            {(): len(state.registry.loaded())},
        )
    )
    return "\n".join(lines) + "\n"


def _metrics_response(state: AppState) -> PlainTextResponse:
    return PlainTextResponse(_scrape(state), media_type="text/plain; version=0.0.4")


def metrics_router(public: bool) -> APIRouter:
    """The /metrics route, open or behind an admin key."""
    metrics = APIRouter(tags=["health"])
    description = "Prometheus text exposition: request latency histograms per route, "
    description += "localize stage timings, stream frames, entries per map, jobs by state."
    responses = {
        200: {
            "content": {
                "text/plain": {"example": ('monoloc_map_entries{map_id="1",map="kitti-00"} 3860\n')}
            }
        }
    }
    if public:

        @metrics.get(
            "/metrics",
            response_class=PlainTextResponse,
            responses=responses,
            summary="Prometheus metrics",
            description=description,
        )
        def open_metrics(state: StateDep) -> PlainTextResponse:
            return _metrics_response(state)
    else:

        @metrics.get(
            "/metrics",
            response_class=PlainTextResponse,
            responses={**responses, **AUTH_ERRORS},
            summary="Prometheus metrics",
            description=description + " Needs an admin key.",
            dependencies=[Depends(require_scope("admin"))],
        )
        def admin_metrics(state: StateDep) -> PlainTextResponse:
            return _metrics_response(state)

    return metrics

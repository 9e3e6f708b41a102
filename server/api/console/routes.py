"""Small JSON routes the console needs beside the resource routes: every entry's planar
pose in one answer (the map plot), the coverage gaps of a selection, an entry's
keypoints, and the live vehicles of a map (a snapshot, or server-sent events).

Scopes: poses, coverage and vehicles are ``localize`` (a vehicle key sees the map and
the live page); keypoints are ``map:write`` like the entry routes.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Query, Request
from fastapi.responses import Response, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field

from monoloc.core.errors import InvalidInputError, NotFoundError
from monoloc.server.api.console.coverage import (
    MAX_POINTS,
    MAX_SAMPLES,
    MIN_RADIUS_M,
    MIN_STEP_M,
    CoverageConfig,
    route_gaps,
    route_length_m,
    sample_count,
    thin_gaps,
)
from monoloc.server.api.console.live import vehicle_board
from monoloc.server.api.convert import AUTH_ERRORS, error_responses
from monoloc.server.api.deps import MapWriteKey, ReadKey, SessionDep, StateDep
from monoloc.server.api.params import DB_ID_MAX, EntryId, MapId
from monoloc.server.api.schemas import TAG_PATTERN
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage.records import EntrySummary

router = APIRouter(prefix="/v1/maps/{map_id}", tags=["console"])
PAGE = 5000  # entries read per query
SSE_PERIOD_S = 0.25
SSE_MAX_S = 30.0  # a stream ends after this long; the page reconnects (lets servers stop)
TagFilter = Annotated[str | None, Query(pattern=TAG_PATTERN, description="Only this tag.")]
RunFilter = Annotated[int | None, Query(ge=1, le=DB_ID_MAX, description="Only this run.")]


class MapPoses(BaseModel):
    """Planar poses (z-up world) of a map's entries, one array per field, id order."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                dict(
                    entry_ids=[1, 2],
                    run_ids=[1, None],
                    x_m=[0.0, 1.5],
                    y_m=[0.0, 0.1],
                    yaw_rad=[0.0, 0.02],
                    tags=[[], ["night"]],
                )
            ]
        }
    )

    entry_ids: list[int]
    run_ids: list[int | None]
    x_m: list[float]
    y_m: list[float]
    yaw_rad: list[float]
    tags: list[list[str]]


class CoverageGap(BaseModel):
    run_id: int | None
    length_m: float
    x_m: list[float]
    y_m: list[float]


class Coverage(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                dict(
                    radius_m=5.0,
                    route_length_m=120.0,
                    gap_length_m=13.5,
                    gaps=[dict(run_id=1, length_m=13.5, x_m=[43.25, 56.75], y_m=[0.0, 0.0])],
                )
            ]
        }
    )
    radius_m: float
    step_m: float = Field(default=0.0, description="The route was sampled every step_m.")
    route_length_m: float = Field(description="Length of every run's route (all entries).")
    gap_length_m: float
    gaps: list[CoverageGap]
    thinned: bool = Field(
        default=False,
        description=f"True when the gaps held more than {MAX_POINTS} points: every k-th "
        "sample is answered (lengths are the whole gaps').",
    )


class EntryKeypoints(BaseModel):
    """The entry's stored keypoints (each has a 3D point) and their depth in its camera;
    with the entry's image (``has_image``), also the keypoints that got no 3D point."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                dict(
                    entry_id=13,
                    image_width_px=1241,
                    image_height_px=376,
                    x_px=[512.4, 640.0],
                    y_px=[180.2, 201.7],
                    depth_m=[12.8, 35.1],
                    has_image=True,
                    without_point_x_px=[20.5],
                    without_point_y_px=[33.0],
                )
            ]
        }
    )

    entry_id: int
    image_width_px: int
    image_height_px: int
    x_px: list[float]
    y_px: list[float]
    depth_m: list[float]
    has_image: bool = Field(description="GET .../image answers the entry's image.")
    without_point_x_px: list[float] = Field(description="Keypoints that got no 3D point.")
    without_point_y_px: list[float]


_VEHICLE_EXAMPLE = {
    "vehicle_id": 1,
    "name": "car",
    "connected": True,
    "connected_for_s": 12.3,
    "frames": 120,
    "dropped": 0,
    "errors": 0,
    "last_seq": 119,
    "last_t_s": 11.9,
    "since_last_frame_s": 0.08,
    "frame_rate_hz": 10.0,
    "latency_ms_p50": 31.5,
    "latency_ms_max": 48.0,
    "estimate": {"x_m": 52.1, "y_m": -1.2, "yaw_rad": 0.03},
    "estimate_source": "vehicle prior",
    "hypotheses": [{"entry_id": 57, "n_inliers": 143, "x_m": 52.0, "y_m": -1.1, "yaw_rad": 0.03}],
}


class VehicleSnapshot(BaseModel):
    """The vehicles streaming to a map (see live.py for each field); ``version`` changes
    with every report."""

    model_config = ConfigDict(
        json_schema_extra={"examples": [{"version": 361, "vehicles": [_VEHICLE_EXAMPLE]}]}
    )
    version: int
    vehicles: list[dict]


def _all_entries(session, map_id: int, tag: str | None = None, run_id: int | None = None):
    maps_repo.get_map(session, map_id)
    out: list[EntrySummary] = []
    while True:
        page = entries_repo.list_entries(
            session, map_id, tag=tag, run_id=run_id, limit=PAGE, offset=len(out)
        )
        out.extend(page)
        if len(page) < PAGE:
            return out


@router.get(
    "/poses",
    response_model=MapPoses,
    responses={**AUTH_ERRORS, **error_responses(404, 422, 503)},
    summary="Planar poses of every entry (the console's map plot)",
)
async def map_poses(
    map_id: MapId,
    state: StateDep,
    session: SessionDep,
    _key: ReadKey,
    tag: TagFilter = None,
    run_id: RunFilter = None,
) -> MapPoses:
    """Computed on the read lane (a whole map's entries; 503 + Retry-After when full)."""
    return await state.run_cpu(_poses, session, map_id, tag, run_id)


def _poses(session, map_id: int, tag: str | None, run_id: int | None) -> MapPoses:
    entries = _all_entries(session, map_id, tag, run_id)
    return MapPoses(
        entry_ids=[e.id for e in entries],
        run_ids=[e.run_id for e in entries],
        x_m=[e.x_m for e in entries],
        y_m=[e.y_m for e in entries],
        yaw_rad=[e.yaw_rad for e in entries],
        tags=[list(e.tags) for e in entries],
    )


@router.get(
    "/coverage",
    response_model=Coverage,
    responses={**AUTH_ERRORS, **error_responses(404, 422, 503)},
    summary="Coverage gaps of a selection of entries along the mapped route",
    description=f"Bounded: `radius_m` >= {MIN_RADIUS_M} m, the route sampled every "
    f"min(radius_m / 4, 1 m); a selection needing more than {MAX_SAMPLES} samples is "
    f"refused with 422 (use a larger radius), and an answer holds at most {MAX_POINTS} "
    "gap points (`thinned`). Computed on the read lane (503 + Retry-After when full).",
)
async def coverage(
    map_id: MapId,
    state: StateDep,
    session: SessionDep,
    _key: ReadKey,
    radius_m: Annotated[
        float,
        Query(ge=MIN_RADIUS_M, le=1000, allow_inf_nan=False, description="Gap radius (m)."),
    ] = CoverageConfig.radius_m,
    tag: TagFilter = None,
    run_id: RunFilter = None,
) -> Coverage:
    """The route is each run's entries in time order; a gap is a stretch of it with no
    entry of the selection (``tag``, ``run_id``) within ``radius_m``."""
    return await state.run_cpu(_coverage, session, map_id, radius_m, tag, run_id)


def _least_radius(routes) -> str:
    """Advice: the smallest radius (3 significant digits, rounded up) within the limit."""
    step_m = MIN_STEP_M
    while step_m < 1.0 and sum(sample_count(r, step_m) for r in routes) > MAX_SAMPLES:
        step_m *= 1.1
    if sum(sample_count(r, min(step_m, 1.0)) for r in routes) > MAX_SAMPLES:
        return "the route is too long for one request at any radius (filter by run_id)"
    digits = 10 ** (np.floor(np.log10(4 * step_m)) - 2)
    return f"use radius_m >= {np.ceil(4 * step_m / digits) * digits:.3g}"


def _coverage(
    session, map_id: int, radius_m: float, tag: str | None, run_id: int | None
) -> Coverage:
    config = CoverageConfig.for_radius(radius_m)
    everything = _all_entries(session, map_id)
    selected = everything if tag is None and run_id is None else None
    if selected is None:
        selected = _all_entries(session, map_id, tag, run_id)
    covered = np.array([(e.x_m, e.y_m) for e in selected], dtype=float).reshape(-1, 2)
    routes: dict[int, np.ndarray] = {}
    by_run: dict[int, list[EntrySummary]] = {}
    for e in everything:
        if e.run_id is not None:
            by_run.setdefault(e.run_id, []).append(e)
    for rid, members in sorted(by_run.items()):
        members.sort(key=lambda e: (e.timestamp_s if e.timestamp_s is not None else 0.0, e.id))
        routes[rid] = np.array([(e.x_m, e.y_m) for e in members], dtype=float)
    total_m = sum(route_length_m(route) for route in routes.values())
    samples = sum(sample_count(route, config.step_m) for route in routes.values())
    if samples > MAX_SAMPLES:
        raise InvalidInputError(
            f"radius_m={radius_m:g}: the map's {total_m:.0f} m of route would take {samples} "
            f"samples every {config.step_m:g} m, over the limit of {MAX_SAMPLES} samples per "
            f"request; {_least_radius(routes.values())}"
        )
    found = [g for rid, route in routes.items() for g in route_gaps(route, covered, config, rid)]
    answered, thinned = thin_gaps(found, MAX_POINTS)
    gaps = []
    for gap in answered:
        xy = np.round(gap.points_xy_m, 3)
        gaps.append(
            CoverageGap(
                run_id=gap.run_id,
                length_m=round(gap.length_m, 3),
                x_m=xy[:, 0].tolist(),
                y_m=xy[:, 1].tolist(),
            )
        )
    return Coverage(
        radius_m=radius_m,
        step_m=config.step_m,
        route_length_m=round(total_m, 3),
        gap_length_m=round(sum(g.length_m for g in found), 3),
        gaps=gaps,
        thinned=thinned,
    )


@router.get(
    "/entries/{entry_id}/keypoints",
    response_model=EntryKeypoints,
    responses={**AUTH_ERRORS, **error_responses(404)},
    summary="An entry's keypoints and their depth",
)
def entry_keypoints(
    map_id: MapId, entry_id: EntryId, session: SessionDep, _key: MapWriteKey
) -> EntryKeypoints:
    summary = entries_repo.get_entry(session, entry_id, map_id=map_id)
    (data,) = entries_repo.get_entry_data(session, [entry_id])
    image = entries_repo.get_entry_image(session, entry_id)
    xy = np.round(np.asarray(data.keypoints_px, dtype=float), 2)
    depth = np.round(np.asarray(data.points_cam, dtype=float)[:, 2], 3)
    without = np.zeros((0, 2))
    if image is not None:
        without = np.round(np.asarray(image.keypoints_without_point_px, dtype=float), 2)
    return EntryKeypoints(
        entry_id=entry_id,
        image_width_px=summary.image_width_px,
        image_height_px=summary.image_height_px,
        x_px=xy[:, 0].tolist(),
        y_px=xy[:, 1].tolist(),
        depth_m=depth.tolist(),
        has_image=image is not None,
        without_point_x_px=without[:, 0].tolist(),
        without_point_y_px=without[:, 1].tolist(),
    )


@router.get(
    "/entries/{entry_id}/image",
    response_class=Response,
    responses={
        200: {
            "content": {
                "image/jpeg": {
                    "schema": {"type": "string", "format": "binary"},
                    "example": "(JPEG bytes: FF D8 FF E0 ...)",
                }
            },
            "description": "A grey JPEG of the entry's reference image, at most 640 px on its "
            "longer side (keypoint pixels scale by its width / the entry's image width).",
        },
        **AUTH_ERRORS,
        **error_responses(404),
    },
    summary="An entry's image (small JPEG)",
)
def entry_image(map_id: MapId, entry_id: EntryId, session: SessionDep, _key: MapWriteKey):
    """404 when the entry does not exist, or was added before monoloc kept entry images."""
    image = entries_repo.get_entry_image(session, entry_id, map_id=map_id)
    if image is None:
        raise NotFoundError(
            f"entry {entry_id} has no stored image (added before monoloc kept entry images)"
        )
    return Response(content=image.jpeg, media_type="image/jpeg")


@router.get(
    "/vehicles",
    response_model=VehicleSnapshot,
    responses={**AUTH_ERRORS, **error_responses(404)},
    summary="Vehicles streaming to the map: latest estimate, hypotheses, rate, latency",
    description="The same snapshots live: `GET /v1/maps/{map_id}/vehicles/events` "
    "(`text/event-stream`, localize scope), one `data:` line per change; it ends after "
    "30 s and the client reconnects.",
)
def vehicles(
    map_id: MapId, request: Request, session: SessionDep, _key: ReadKey
) -> VehicleSnapshot:
    maps_repo.get_map(session, map_id)
    return VehicleSnapshot(**vehicle_board(request.app).snapshot(map_id))


@router.get(
    "/vehicles/events",
    include_in_schema=False,  # an open-ended stream: described on GET .../vehicles
    response_class=StreamingResponse,
    responses={
        200: {
            "description": "One ``data:`` line per snapshot (the /vehicles answer).",
            "content": {
                "text/event-stream": {
                    "example": "data: " + json.dumps({"version": 361, "vehicles": []}) + "\n\n"
                }
            },
        },
        **AUTH_ERRORS,
        **error_responses(404),
    },
    summary="The same as server-sent events, one snapshot per change",
)
def vehicle_events(
    map_id: MapId, request: Request, session: SessionDep, _key: ReadKey
) -> StreamingResponse:
    """``text/event-stream``: a ``data:`` snapshot at once and after every change
    (checked every 0.25 s); the stream ends after 30 s and the client reconnects."""
    maps_repo.get_map(session, map_id)
    board = vehicle_board(request.app)

    async def events() -> AsyncIterator[str]:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + SSE_MAX_S
        sent = -1
        while loop.time() < deadline and not await request.is_disconnected():
            snapshot = board.snapshot(map_id)
            if snapshot["version"] != sent:
                sent = snapshot["version"]
                yield f"data: {json.dumps(snapshot)}\n\n"
            await asyncio.sleep(SSE_PERIOD_S)

    # X-Accel-Buffering: a proxy in front (nginx) passes each event on at once
    headers = {"Cache-Control": "no-store", "X-Accel-Buffering": "no"}
    return StreamingResponse(events(), media_type="text/event-stream", headers=headers)

"""Entries (map:write): add one reference image with its pose and 3D source, list with
filters, get, delete, re-tag. Adds and deletes reach the live index right after their
database commit, so the next query sees them."""

from __future__ import annotations

from typing import Annotated

import numpy as np
from fastapi import APIRouter, File, Form, Query, Response, UploadFile, status

from monoloc.core.errors import InvalidInputError
from monoloc.server.api import convert
from monoloc.server.api.consistency import MAP_VERSION_HEADER
from monoloc.server.api.convert import AUTH_ERRORS, error_responses
from monoloc.server.api.deps import MapWriteKey, RegistryDep, SessionDep, StateDep
from monoloc.server.api.entry_upload import NewEntryForm, add_entry_from_form
from monoloc.server.api.guard import GuardedRoute, body_limit
from monoloc.server.api.params import DB_ID_MAX, EntryId, Limit, MapId, Offset
from monoloc.server.api.schemas import (
    TAG_LIST_PATTERN,
    TAG_PATTERN,
    EntryCreated,
    EntryDetail,
    EntryList,
    EntryPublic,
    TagsUpdate,
)
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage.entry_checks import normalise_tags
from monoloc.server.storage.records import Area

AREA_MAX_M = 1e7  # larger than any map's world frame (the Earth's radius is 6.4e6 m)
router = APIRouter(prefix="/v1/maps/{map_id}/entries", tags=["entries"], route_class=GuardedRoute)


@router.post(
    "",
    response_model=EntryCreated,
    openapi_extra=body_limit("entry"),
    status_code=status.HTTP_201_CREATED,
    responses={
        200: {
            "description": "The same image was already in the map (nothing added).",
            "model": EntryCreated,
        },
        **AUTH_ERRORS,
        **error_responses(404, 413, 415, 422),
    },
    summary="Add one reference image",
)
async def add_entry(
    map_id: MapId,
    response: Response,
    state: StateDep,
    _key: MapWriteKey,
    image: Annotated[UploadFile, File(description="PNG or JPEG, the map camera's size.")],
    T_world_from_cam: Annotated[
        str,
        Form(
            description="16 numbers, row-major, as a JSON "
            "array or comma/space separated (z-up world)."
        ),
    ],
    depth: Annotated[
        UploadFile | None,
        File(description="16-bit depth PNG registered to the image; needs depth_scale."),
    ] = None,
    depth_scale: Annotated[
        float | None,
        Form(gt=0, allow_inf_nan=False, description="Raw depth units per metre (TUM: 5000)."),
    ] = None,
    lidar: Annotated[
        UploadFile | None,
        File(description="LiDAR scan, KITTI .bin (float32 x, y, z, r); needs T_cam_from_lidar."),
    ] = None,
    T_cam_from_lidar: Annotated[str | None, Form(description="16 numbers, row-major.")] = None,
    tags: Annotated[
        str | None,
        Form(pattern=TAG_LIST_PATTERN, description="Comma-separated, e.g. night,off-center."),
    ] = None,
    timestamp_s: Annotated[
        float | None, Form(allow_inf_nan=False, description="Capture time (s).")
    ] = None,
) -> EntryCreated:
    """Builds the entry (ORB keypoints with a 3D point from the depth image or the
    projected LiDAR scan, VLAD) and stores it. The same image twice is stored once
    (200 with created false)."""
    form = NewEntryForm(
        image=await image.read(),
        T_world_from_cam=T_world_from_cam,
        depth=await depth.read() if depth is not None else None,
        depth_scale=depth_scale,
        lidar=await lidar.read() if lidar is not None else None,
        T_cam_from_lidar=T_cam_from_lidar,
        tags=tuple(normalise_tags(t for t in (tags or "").split(",") if t.strip())),
        timestamp_s=timestamp_s,
    )
    created = await add_entry_from_form(state, map_id, form)
    response.headers[MAP_VERSION_HEADER] = str(created.map_version)
    if not created.created:
        response.status_code = status.HTTP_200_OK
    return created


@router.get(
    "",
    response_model=EntryList,
    responses={**AUTH_ERRORS, **error_responses(404, 422)},
    summary="List entries",
)
def list_entries(
    map_id: MapId,
    session: SessionDep,
    _key: MapWriteKey,
    tag: Annotated[str | None, Query(pattern=TAG_PATTERN, description="Only this tag.")] = None,
    run_id: Annotated[int | None, Query(ge=1, le=DB_ID_MAX)] = None,
    x_m: Annotated[
        float | None,
        Query(
            ge=-AREA_MAX_M,
            le=AREA_MAX_M,
            allow_inf_nan=False,
            description="Area centre x (m). The area filter takes x_m, y_m and radius_m "
            "together (422 if only some are given).",
        ),
    ] = None,
    y_m: Annotated[
        float | None,
        Query(ge=-AREA_MAX_M, le=AREA_MAX_M, allow_inf_nan=False, description="Area centre y (m)."),
    ] = None,
    radius_m: Annotated[
        float | None,
        Query(gt=0, le=AREA_MAX_M, allow_inf_nan=False, description="Area radius (m)."),
    ] = None,
    limit: Limit = 100,
    offset: Offset = 0,
) -> EntryList:
    """Entries in id order, filtered by tag, run and/or a disc (x_m, y_m, radius_m)."""
    maps_repo.get_map(session, map_id)
    area_values = (x_m, y_m, radius_m)
    if any(v is not None for v in area_values) and None in area_values:
        raise InvalidInputError("an area filter needs x_m, y_m and radius_m together")
    area = Area(x_m, y_m, radius_m) if x_m is not None else None  # type: ignore[arg-type]
    filters = dict(tag=tag, run_id=run_id, area=area)
    items = entries_repo.list_entries(session, map_id, limit=limit, offset=offset, **filters)
    return EntryList(
        items=[convert.entry_public(e) for e in items],
        total=entries_repo.count_entries(session, map_id, **filters),
        limit=limit,
        offset=offset,
    )


@router.get(
    "/{entry_id}",
    response_model=EntryDetail,
    responses={**AUTH_ERRORS, **error_responses(404)},
    summary="Get an entry",
)
def get_entry(
    map_id: MapId, entry_id: EntryId, session: SessionDep, _key: MapWriteKey
) -> EntryDetail:
    """The entry with its full pose T_world_from_cam."""
    summary = entries_repo.get_entry(session, entry_id, map_id=map_id)
    (data,) = entries_repo.get_entry_data(session, [entry_id])
    return convert.entry_detail(summary, np.asarray(data.T_world_from_cam))


@router.delete(
    "/{entry_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    responses={**AUTH_ERRORS, **error_responses(404)},
    summary="Delete an entry",
)
def delete_entry(
    map_id: MapId, entry_id: EntryId, session: SessionDep, registry: RegistryDep, _key: MapWriteKey
) -> Response:
    """Removes the entry; the next query no longer retrieves it. The map version the
    deletion produced is in the X-Map-Version header."""
    version = entries_repo.delete_entry(session, entry_id, map_id=map_id)
    session.commit()
    registry.entries_removed(map_id, [entry_id], version)
    headers = {MAP_VERSION_HEADER: str(version)}
    return Response(status_code=status.HTTP_204_NO_CONTENT, headers=headers)


@router.patch(
    "/{entry_id}",
    response_model=EntryPublic,
    responses={**AUTH_ERRORS, **error_responses(404, 422)},
    summary="Re-tag an entry",
)
def retag_entry(
    map_id: MapId,
    entry_id: EntryId,
    body: TagsUpdate,
    session: SessionDep,
    registry: RegistryDep,
    response: Response,
    _key: MapWriteKey,
) -> EntryPublic:
    """Replaces the entry's tags (lower-cased, duplicates dropped); the map version it
    produced is in the X-Map-Version header."""
    summary = entries_repo.set_entry_tags(session, entry_id, body.tags, map_id=map_id)
    version = maps_repo.get_map(session, map_id).version
    session.commit()
    response.headers[MAP_VERSION_HEADER] = str(version)
    registry.entry_retagged(map_id, entry_id)
    return convert.entry_public(summary)

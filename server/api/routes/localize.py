"""``POST /v1/maps/{map_id}/localize``: pose hypotheses for one PNG/JPEG frame."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, File, Form, Header, Request, UploadFile

from monoloc.server.api.consistency import await_map_version
from monoloc.server.api.convert import AUTH_ERRORS, error_responses
from monoloc.server.api.deps import LocalizeKey, StateDep
from monoloc.server.api.guard import GuardedRoute, body_limit
from monoloc.server.api.localizing import localize_bytes
from monoloc.server.api.params import DB_ID_MAX, MapId
from monoloc.server.api.schemas_localize import LocalizeOptions, LocalizeResponse

router = APIRouter(prefix="/v1/maps/{map_id}", tags=["localize"], route_class=GuardedRoute)


@router.post(
    "/localize",
    response_model=LocalizeResponse,
    openapi_extra=body_limit("image"),
    responses={
        **AUTH_ERRORS,
        **error_responses(404, 413, 415, 422),
        503: {
            "description": "Overloaded, deadline passed or stale replica; see Retry-After "
            "(whole seconds) and Retry-After-Ms (the same wait in milliseconds)."
        },
    },
    summary="Localize one frame",
)
async def localize(
    map_id: MapId,
    request: Request,
    state: StateDep,
    _key: LocalizeKey,
    image: Annotated[UploadFile, File(description="The query frame, PNG or JPEG.")],
    options: Annotated[LocalizeOptions, Form()],
    min_map_version: Annotated[
        int | None,
        Header(
            alias="X-Min-Map-Version",
            ge=0,
            le=DB_ID_MAX,
            description="Answer from this map version or newer (read-your-writes after a "
            "write's map_version); 503 stale_replica if this replica cannot reach it soon.",
        ),
    ] = None,
) -> LocalizeResponse:
    """Blur + ORB + VLAD, retrieval of the k nearest entries (inside the prior, if
    given), matching and PnP per entry. Answers the hypotheses (most inliers first),
    the retrieval, per-stage timings (ms) and the map version they were computed on.
    Every option may also be sent as a query parameter (the form wins, field by field;
    the form's own options must form complete groups)."""
    options = options.over(request.query_params)
    wait_s = state.settings.min_version_wait_ms / 1e3
    await await_map_version(state.registry, map_id, min_map_version, wait_s)
    return await localize_bytes(state, map_id, await image.read(), options)

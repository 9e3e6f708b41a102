"""``POST /v1/maps/{map_id}/localize``: pose hypotheses for one PNG/JPEG frame."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, File, Form, Request, UploadFile

from monoloc.server.api.convert import AUTH_ERRORS, error_responses
from monoloc.server.api.deps import LocalizeKey, StateDep
from monoloc.server.api.localizing import localize_bytes, parse_options
from monoloc.server.api.schemas_localize import LocalizeResponse

router = APIRouter(prefix="/v1/maps/{map_id}", tags=["localize"])

OPTION_NAMES = (
    "fx",
    "fy",
    "cx",
    "cy",
    "prior_x_m",
    "prior_y_m",
    "prior_radius_m",
    "prior_yaw_rad",
    "prior_yaw_tolerance_rad",
    "k",
    "seed",
)
OptionalFloat = Annotated[float | None, Form()]


@router.post(
    "/localize",
    response_model=LocalizeResponse,
    responses={**AUTH_ERRORS, **error_responses(404, 413, 415, 422)},
    summary="Localize one frame",
)
async def localize(
    map_id: int,
    request: Request,
    state: StateDep,
    _key: LocalizeKey,
    image: Annotated[UploadFile, File(description="The query frame, PNG or JPEG.")],
    fx: Annotated[
        float | None,
        Form(
            description="Focal length x (px); fx, fy, cx, cy all or none (none: the map's camera)."
        ),
    ] = None,
    fy: OptionalFloat = None,
    cx: OptionalFloat = None,
    cy: OptionalFloat = None,
    prior_x_m: Annotated[
        float | None, Form(description="Prior position x (m); with prior_y_m and prior_radius_m.")
    ] = None,
    prior_y_m: OptionalFloat = None,
    prior_radius_m: OptionalFloat = None,
    prior_yaw_rad: Annotated[
        float | None, Form(description="Prior heading; with prior_yaw_tolerance_rad.")
    ] = None,
    prior_yaw_tolerance_rad: OptionalFloat = None,
    k: Annotated[int | None, Form(description="Entries to retrieve (default 10).")] = None,
    seed: Annotated[
        int | None,
        Form(description="RANSAC seed (default: server draws one; the answer reports it)."),
    ] = None,
) -> LocalizeResponse:
    """Blur + ORB + VLAD, retrieval of the k nearest entries (inside the prior, if
    given), matching and PnP per entry. Answers the hypotheses (most inliers first),
    the retrieval, per-stage timings (ms) and the map version they were computed on.
    Every optional field may also be sent as a query parameter (the form wins)."""
    form = dict(
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        prior_x_m=prior_x_m,
        prior_y_m=prior_y_m,
        prior_radius_m=prior_radius_m,
        prior_yaw_rad=prior_yaw_rad,
        prior_yaw_tolerance_rad=prior_yaw_tolerance_rad,
        k=k,
        seed=seed,
    )
    values = {
        n: form[n] if form[n] is not None else request.query_params.get(n) for n in OPTION_NAMES
    }
    options = parse_options(values)
    data = await image.read()
    return await localize_bytes(state, map_id, data, options)

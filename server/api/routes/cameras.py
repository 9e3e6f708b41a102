"""Cameras: a vehicle registers its camera once (``POST /v1/cameras``, scope localize)
and names it by id in every frame after (``camera_id`` of ``POST .../localize`` and of
the stream header) instead of sending its intrinsics each time.

Scopes: registering needs ``localize`` (what a vehicle's key has; admin too); any valid
key lists and reads cameras, as it reads maps; a camera is deleted by the key that
registered it, or by an admin key (403 otherwise). A camera belongs to no map, so a key
limited to some maps registers and sees every camera as any other key does (a camera
holds intrinsics, no map data). Cameras are never changed: delete and register again.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Response, status

from monoloc.server.api.convert import AUTH_ERRORS, error_responses
from monoloc.server.api.deps import LocalizeKey, ReadKey, SessionDep, StateDep
from monoloc.server.api.errors import ForbiddenError
from monoloc.server.api.guard import GuardedRoute
from monoloc.server.api.params import Limit, id_path
from monoloc.server.api.schemas_cameras import CameraCreate, CameraList, CameraPublic
from monoloc.server.storage import cameras as cameras_repo

router = APIRouter(prefix="/v1/cameras", tags=["cameras"], route_class=GuardedRoute)
CameraId = Annotated[int, id_path("camera")]


@router.post(
    "",
    response_model=CameraPublic,
    status_code=status.HTTP_201_CREATED,
    responses={**AUTH_ERRORS, **error_responses(422)},
    summary="Register a camera",
)
def register_camera(body: CameraCreate, session: SessionDep, key: LocalizeKey) -> CameraPublic:
    """Stores the camera and answers its ``id``, which frames then send as
    ``camera_id``. An unknown distortion model, or coefficients that do not fit the
    model, answer 422 naming it."""
    record = cameras_repo.create_camera(session, body.name, body.intrinsics(), key.id)
    session.commit()
    return CameraPublic.of(record)


@router.get("", response_model=CameraList, responses=AUTH_ERRORS, summary="List cameras")
def list_cameras(session: SessionDep, _key: ReadKey, limit: Limit = 1000) -> CameraList:
    """The registered cameras, oldest first (at most ``limit``)."""
    return CameraList(items=[CameraPublic.of(r) for r in cameras_repo.list_cameras(session, limit)])


@router.get(
    "/{camera_id}",
    response_model=CameraPublic,
    responses={**AUTH_ERRORS, **error_responses(404)},
    summary="Get a camera",
)
def get_camera(camera_id: CameraId, session: SessionDep, _key: ReadKey) -> CameraPublic:
    return CameraPublic.of(cameras_repo.get_camera(session, camera_id))


@router.delete(
    "/{camera_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    responses={**AUTH_ERRORS, **error_responses(404)},
    summary="Delete a camera",
)
def delete_camera(
    camera_id: CameraId, session: SessionDep, state: StateDep, key: LocalizeKey
) -> Response:
    """By the key that registered it, or an admin key (403 otherwise). Frames that still
    name it are answered 404 from then on (other replicas within ``MONOLOC_KEY_CACHE_S``)."""
    record = cameras_repo.get_camera(session, camera_id)
    if record.key_id != key.id and not key.has_scope("admin"):
        raise ForbiddenError(
            f"camera {camera_id} was registered by another key; only that key or an admin "
            "key may delete it"
        )
    cameras_repo.delete_camera(session, camera_id)
    session.commit()
    state.cameras.forget(camera_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)

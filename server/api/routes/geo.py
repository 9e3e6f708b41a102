"""A map's geographic reference (get: localize; put and delete: map:write). With one,
localize and stream answers carry each hypothesis as an OGC GeoPose (monoloc/core/geo.py).
A vehicle's localize key reads it on purpose: ``monoloc drive`` places its own filter's
track with it, and the reference tells a vehicle nothing its answers' GeoPoses do not.

This replica answers with a new reference at once; other replicas pick it up when they
next check the map (``MONOLOC_REPLICA_SYNC_S``), as with a calibration."""

from __future__ import annotations

from fastapi import APIRouter, Response, status

from monoloc.core.errors import NotFoundError
from monoloc.server.api.convert import AUTH_ERRORS, error_responses, geo_reference_public
from monoloc.server.api.deps import MapWriteKey, ReadKey, RegistryDep, SessionDep
from monoloc.server.api.guard import GuardedRoute
from monoloc.server.api.params import MapId
from monoloc.server.api.schemas import GeoReferencePublic, GeoReferenceUpdate
from monoloc.server.storage import maps as maps_repo

router = APIRouter(
    prefix="/v1/maps/{map_id}/geo-reference", tags=["maps"], route_class=GuardedRoute
)


def _refresh(registry, map_id: int) -> None:
    if map_id in registry.loaded():
        registry.catch_up(map_id)


@router.get(
    "",
    response_model=GeoReferencePublic,
    responses={**AUTH_ERRORS, **error_responses(404)},
    summary="Get the map's geographic reference",
)
def get_geo_reference(map_id: MapId, session: SessionDep, _key: ReadKey) -> GeoReferencePublic:
    """404 when the map does not exist or is not geo-referenced."""
    public = geo_reference_public(maps_repo.get_map(session, map_id).geo_reference)
    if public is None:
        raise NotFoundError(f"map {map_id} has no geographic reference")
    return public


@router.put(
    "",
    response_model=GeoReferencePublic,
    responses={**AUTH_ERRORS, **error_responses(404, 422)},
    summary="Set the map's geographic reference",
)
def put_geo_reference(
    map_id: MapId,
    body: GeoReferenceUpdate,
    session: SessionDep,
    registry: RegistryDep,
    _key: MapWriteKey,
) -> GeoReferencePublic:
    """Exactly one of ``origin`` (WGS84 lat/lon/h of the world origin and the compass
    heading of its +X axis) and ``T_ecef_from_world`` (a rigid transform near the Earth's
    surface); 422 otherwise. Replaces the previous reference; entries are unchanged."""
    maps_repo.get_map(session, map_id)
    record = maps_repo.set_geo_reference(session, map_id, body.to_reference())
    session.commit()
    _refresh(registry, map_id)
    return geo_reference_public(record.geo_reference)


@router.delete(
    "",
    status_code=status.HTTP_204_NO_CONTENT,
    responses={**AUTH_ERRORS, **error_responses(404)},
    summary="Forget the map's geographic reference",
)
def delete_geo_reference(
    map_id: MapId, session: SessionDep, registry: RegistryDep, _key: MapWriteKey
) -> Response:
    maps_repo.set_geo_reference(session, map_id, None)
    session.commit()
    _refresh(registry, map_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)

"""Maps: create (admin), list and get (localize: vehicles look maps up), delete (admin),
and vocabulary-change jobs (admin)."""

from __future__ import annotations

from fastapi import APIRouter, Response, status

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import ConflictError
from monoloc.server.api import convert
from monoloc.server.api.convert import AUTH_ERRORS, error_responses
from monoloc.server.api.deps import AdminKey, ReadKey, RegistryDep, SessionDep, StateDep
from monoloc.server.api.guard import GuardedRoute
from monoloc.server.api.params import MapId
from monoloc.server.api.schemas import JobPublic, MapCreate, MapDetail, MapList, VocabularyJobCreate
from monoloc.server.jobs import store as jobs_repo
from monoloc.server.jobs.vocabulary import JOB_KIND, VocabularyParams
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage import runs as runs_repo

router = APIRouter(prefix="/v1/maps", tags=["maps"], route_class=GuardedRoute)


def _vocabulary_id(session, ref: str) -> int:
    """'default' (stored on first use) or the hash of a stored vocabulary."""
    if ref == "default":
        from monoloc.server.vision.vocabulary import load_default_vocabulary

        default = load_default_vocabulary()
        record, _ = maps_repo.get_or_create_vocabulary(
            session, default.centres, default.description or "default vocabulary"
        )
        return record.id
    return maps_repo.get_vocabulary_by_hash(session, ref).id


def _detail(session, registry, map_id: int) -> MapDetail:
    record = maps_repo.get_map(session, map_id)
    public = convert.map_public(record, maps_repo.get_vocabulary(session, record.vocabulary_id))
    loaded = registry.loaded()
    return MapDetail(
        **public.model_dump(),
        n_runs=len(runs_repo.list_runs(session, map_id)),
        tag_counts=entries_repo.tag_counts(session, map_id),
        index_loaded=map_id in loaded,
        indexed_entries=loaded.get(map_id),
    )


@router.post(
    "",
    response_model=MapDetail,
    status_code=status.HTTP_201_CREATED,
    responses={**AUTH_ERRORS, **error_responses(404, 409, 422)},
    summary="Create a map",
)
def create_map(
    body: MapCreate, session: SessionDep, registry: RegistryDep, _key: AdminKey
) -> MapDetail:
    """An empty map with its camera and vocabulary ('default' or a stored hash)."""
    c = body.camera
    camera = CameraIntrinsics(c.fx, c.fy, c.cx, c.cy, c.width_px, c.height_px)
    vocabulary_id = _vocabulary_id(session, body.vocabulary)
    geo = body.geo_reference.to_reference() if body.geo_reference is not None else None
    record = maps_repo.create_map(session, body.name, camera, vocabulary_id)
    if geo is not None:
        maps_repo.set_geo_reference(session, record.id, geo)
    session.commit()
    registry.get(record.id)  # an empty index, so /readyz and queries see the map at once
    return _detail(session, registry, record.id)


@router.get("", response_model=MapList, responses=AUTH_ERRORS, summary="List maps")
def list_maps(session: SessionDep, key: ReadKey) -> MapList:
    """Every map, or the maps the key is limited to."""
    vocabularies: dict[int, object] = {}
    items = []
    for record in maps_repo.list_maps(session):
        if not key.can_see_map(record.id):
            continue
        if record.vocabulary_id not in vocabularies:
            vocabularies[record.vocabulary_id] = maps_repo.get_vocabulary(
                session, record.vocabulary_id
            )
        items.append(convert.map_public(record, vocabularies[record.vocabulary_id]))
    return MapList(items=items)


@router.get(
    "/{map_id}",
    response_model=MapDetail,
    responses={**AUTH_ERRORS, **error_responses(404)},
    summary="Get a map",
)
def get_map(map_id: MapId, session: SessionDep, registry: RegistryDep, _key: ReadKey) -> MapDetail:
    """Counts (entries, runs, tags), version, vocabulary, calibration status, index state."""
    return _detail(session, registry, map_id)


@router.delete(
    "/{map_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    responses={**AUTH_ERRORS, **error_responses(404, 409)},
    summary="Delete a map",
)
def delete_map(
    map_id: MapId, session: SessionDep, registry: RegistryDep, _key: AdminKey
) -> Response:
    """Deletes the map with its runs and entries, and its index file. Refused (409)
    while one of its jobs is queued or running."""
    maps_repo.get_map(session, map_id)
    busy = jobs_repo.list_jobs(session, map_id=map_id, states=("queued", "running"))
    if busy:
        raise ConflictError(
            f"map {map_id} has active jobs {[j.id for j in busy]}; cancel them first"
        )
    maps_repo.delete_map(session, map_id)
    session.commit()
    registry.forget(map_id, delete_file=True)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.post(
    "/{map_id}/vocabulary/jobs",
    response_model=JobPublic,
    status_code=status.HTTP_202_ACCEPTED,
    responses={**AUTH_ERRORS, **error_responses(404, 422)},
    summary="Change the map's vocabulary (job)",
)
def vocabulary_job(
    map_id: MapId, body: VocabularyJobCreate, session: SessionDep, state: StateDep, _key: AdminKey
) -> JobPublic:
    """Switch to 'default' or a stored vocabulary hash; the job recomputes every entry's
    VLAD while the map keeps answering queries. (Training a vocabulary on the map's own
    data happens with an upload: train_vocabulary=true.)"""
    maps_repo.get_map(session, map_id)
    params = VocabularyParams.create(
        vocabulary=body.vocabulary, vocabulary_id=_vocabulary_id(session, body.vocabulary)
    )
    job = jobs_repo.create_job(
        session, JOB_KIND, map_id=map_id, params=params.model_dump(mode="json")
    )
    session.commit()
    state.jobs.submit(job.id)
    return JobPublic.model_validate(job)

"""Jobs (map:write): list, get (state, progress, result), resume, cancel. A key limited
to some maps sees and acts on their jobs only (403 for another map's job)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query

from monoloc.server.api.convert import AUTH_ERRORS, error_responses
from monoloc.server.api.deps import MapWriteKey, SessionDep, StateDep, check_map_access
from monoloc.server.api.errors import ForbiddenError
from monoloc.server.api.guard import GuardedRoute
from monoloc.server.api.params import DB_ID_MAX, JobId, Limit, Offset
from monoloc.server.api.schemas import JobList, JobPublic
from monoloc.server.jobs import store as jobs_repo
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.records import ApiKeyRecord, JobRecord

router = APIRouter(prefix="/v1/jobs", tags=["jobs"], route_class=GuardedRoute)

JOB_STATES = ("queued", "running", "done", "failed", "interrupted")
JobState = Literal["queued", "running", "done", "failed", "interrupted"]


def _visible_job(session, job_id: int, key: ApiKeyRecord) -> JobRecord:
    job = jobs_repo.get_job(session, job_id)
    if key.maps is not None:
        if job.map_id is None:
            raise ForbiddenError(f"job {job_id} belongs to no map; this key is limited to maps")
        check_map_access(key, job.map_id)
    return job


@router.get(
    "",
    response_model=JobList,
    responses={**AUTH_ERRORS, **error_responses(422)},
    summary="List jobs",
)
def list_jobs(
    session: SessionDep,
    key: MapWriteKey,
    map_id: Annotated[int | None, Query(ge=1, le=DB_ID_MAX)] = None,
    state: Annotated[list[JobState] | None, Query(max_length=len(JOB_STATES))] = None,
    limit: Limit = 100,
    offset: Offset = 0,
) -> JobList:
    """Newest first, optionally of one map and/or in the given states (only the jobs of
    the key's maps, for a key limited to maps)."""
    check_map_access(key, map_id)
    jobs = jobs_repo.list_jobs(
        session, map_id=map_id, states=state, limit=limit, offset=offset, map_ids=key.maps
    )
    return JobList(items=[JobPublic.model_validate(j) for j in jobs])


@router.get(
    "/{job_id}",
    response_model=JobPublic,
    responses={**AUTH_ERRORS, **error_responses(404)},
    summary="Get a job",
)
def get_job(job_id: JobId, session: SessionDep, key: MapWriteKey) -> JobPublic:
    """State (queued, running, done, failed, interrupted), progress 0..1, message, error
    and, when done, the result (an ingestion's summary: entries added, skips and why)."""
    return JobPublic.model_validate(_visible_job(session, job_id, key))


@router.post(
    "/{job_id}/resume",
    response_model=JobPublic,
    responses={**AUTH_ERRORS, **error_responses(404, 409)},
    summary="Resume a job",
)
def resume_job(job_id: JobId, state: StateDep, key: MapWriteKey) -> JobPublic:
    """Re-queue an interrupted or failed job (409 otherwise). Ingestion skips the frames
    already in the map, so nothing is added twice."""
    with session_scope(state.sessions) as session:
        _visible_job(session, job_id, key)
    return JobPublic.model_validate(state.jobs.resume(job_id))


@router.post(
    "/{job_id}/cancel",
    response_model=JobPublic,
    responses={**AUTH_ERRORS, **error_responses(404, 409)},
    summary="Cancel a job",
)
def cancel_job(job_id: JobId, state: StateDep, key: MapWriteKey) -> JobPublic:
    """Stop a queued or running job: it ends 'interrupted' (what it committed stays) and
    may be resumed later."""
    with session_scope(state.sessions) as session:
        _visible_job(session, job_id, key)
    return JobPublic.model_validate(state.jobs.cancel(job_id))

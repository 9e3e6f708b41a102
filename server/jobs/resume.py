"""Resuming a job. Work cut off by a crash or a shutdown is taken over by a replica
(``monoloc.server.jobs.lease``); a job that ended ``interrupted`` (cancelled) or
``failed`` comes back only when asked (``POST /v1/jobs/{id}/resume``). Every kind is
idempotent (entries by image hash, VLADs by vocabulary id, a calibration replaces the
previous one and is seeded), so a resumed job does only the work that was missing."""

from __future__ import annotations

from collections.abc import Collection

from sqlalchemy.orm import Session

from monoloc.core.errors import ConflictError
from monoloc.server.jobs import store
from monoloc.server.jobs.uploads import upload_dir_of
from monoloc.server.settings import Settings
from monoloc.server.storage.records import JobRecord

RESUMABLE_STATES = ("interrupted", "failed")


def requeue_job(
    session: Session, job_id: int, *, kinds: Collection[str], settings: Settings
) -> JobRecord:
    """Move an interrupted or failed job of one of ``kinds`` back to ``queued``;
    ConflictError if it is in another state, of an unknown kind or its upload is gone."""
    job = store.get_job(session, job_id)
    if job.state not in RESUMABLE_STATES:
        raise ConflictError(f"job {job_id} is {job.state}; only interrupted or failed jobs resume")
    if job.kind not in kinds:
        raise ConflictError(f"job {job_id} is of kind {job.kind!r}, unknown here")
    upload = upload_dir_of(job, settings)
    if upload is not None and not upload.is_dir():
        raise ConflictError(f"the upload of job {job_id} is gone; upload the run again")
    return store.update_job(session, job_id, state="queued", progress=0.0, message="resumed")

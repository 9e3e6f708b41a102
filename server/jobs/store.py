"""The durable store of jobs: the SQL of the ``jobs`` table (state, progress, message,
error, result of each ingestion, vocabulary change, calibration). Never commits.

Job states: queued -> running -> done | failed | interrupted. An interrupted or failed
job may be queued or run again (resumed); done is final. Which process runs a job is a
lease (``monoloc.server.jobs.lease``): work whose holder died is taken over, not marked.
:func:`mark_interrupted_jobs` remains for tools that stop every job of a database.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from monoloc.core.errors import ConflictError, InvalidInputError, NotFoundError
from monoloc.server.storage.maps import get_map
from monoloc.server.storage.models import JOB_STATES, Job, Run, utc_now
from monoloc.server.storage.records import JobRecord
from monoloc.server.storage.runs import check_kind, get_run

TERMINAL_JOB_STATES = ("done", "failed", "interrupted")
_JOB_TRANSITIONS = {
    "queued": {"queued", "running", "done", "failed", "interrupted"},
    "running": {"running", "done", "failed", "interrupted"},
    "interrupted": {"queued", "running", "failed", "interrupted"},
    "failed": {"queued", "running", "failed"},
    "done": {"done"},
}


def _job_row(session: Session, job_id: int) -> Job:
    row = session.get(Job, job_id, populate_existing=True)
    if row is None:
        raise NotFoundError(f"job {job_id} does not exist")
    return row


def create_job(
    session: Session,
    kind: str,
    *,
    map_id: int | None = None,
    run_id: int | None = None,
    params: Mapping[str, Any] | None = None,
    message: str = "",
) -> JobRecord:
    """Record a queued job; ``params`` (JSON) is what is needed to (re)run it."""
    if map_id is not None:
        get_map(session, map_id)
    if run_id is not None:
        get_run(session, run_id)
    row = Job(
        kind=check_kind(kind, "job"),
        map_id=map_id,
        run_id=run_id,
        state="queued",
        progress=0.0,
        message=message,
        params=dict(params or {}),
    )
    session.add(row)
    session.flush()
    return JobRecord.model_validate(row)


def get_job(session: Session, job_id: int) -> JobRecord:
    return JobRecord.model_validate(_job_row(session, job_id))


def list_jobs(
    session: Session,
    *,
    map_id: int | None = None,
    states: Iterable[str] | None = None,
    limit: int = 100,
    offset: int = 0,
    map_ids: Iterable[int] | None = None,
) -> list[JobRecord]:
    """Jobs, newest first, optionally of one map, of some maps (``map_ids``) and/or in
    the given states."""
    stmt = select(Job).execution_options(populate_existing=True)
    if map_id is not None:
        stmt = stmt.where(Job.map_id == map_id)
    if map_ids is not None:
        stmt = stmt.where(Job.map_id.in_(list(map_ids)))
    if states is not None:
        stmt = stmt.where(Job.state.in_(list(states)))
    stmt = stmt.order_by(Job.id.desc()).limit(max(0, limit)).offset(max(0, offset))
    return [JobRecord.model_validate(r) for r in session.scalars(stmt)]


def update_job(
    session: Session,
    job_id: int,
    *,
    state: str | None = None,
    progress: float | None = None,
    message: str | None = None,
    error: str | None = None,
    result: Mapping[str, Any] | None = None,
) -> JobRecord:
    """Move a job to ``state`` and/or record progress (0..1), message, error, result.

    ConflictError on a forbidden transition (e.g. anything after done). Entering a
    terminal state sets ``finished_at``; done sets progress to 1; re-queueing or
    re-running clears ``finished_at`` and the old error.
    """
    row = _job_row(session, job_id)
    if state is not None:
        if state not in JOB_STATES:
            raise InvalidInputError(f"job state must be one of {JOB_STATES}, got {state!r}")
        if state not in _JOB_TRANSITIONS[row.state]:
            raise ConflictError(f"job {job_id} cannot go from {row.state} to {state}")
        if state in TERMINAL_JOB_STATES:
            if row.state != state or row.finished_at is None:
                row.finished_at = utc_now()
            if state == "done":
                row.progress = 1.0
        else:
            row.finished_at = None
            if row.state in ("failed", "interrupted"):
                row.error = None
        row.state = state
    if progress is not None:
        if not math.isfinite(progress) or not 0.0 <= progress <= 1.0:
            raise InvalidInputError(f"job progress must be within [0, 1], got {progress}")
        row.progress = float(progress)
    if message is not None:
        row.message = message
    if error is not None:
        row.error = error
    if result is not None:
        row.result = dict(result)
    row.updated_at = utc_now()
    session.flush()
    return JobRecord.model_validate(row)


def mark_interrupted_jobs(
    session: Session, message: str = "interrupted: the server stopped while the job was active"
) -> list[int]:
    """Mark queued and running jobs (and pending/running runs) as interrupted; call once
    at start-up, before any worker runs. Returns the ids of the jobs marked."""
    now = utc_now()
    ids = list(session.scalars(select(Job.id).where(Job.state.in_(("queued", "running")))))
    if ids:
        session.execute(
            update(Job)
            .where(Job.id.in_(ids))
            .values(state="interrupted", message=message, updated_at=now, finished_at=now)
            .execution_options(synchronize_session=False)
        )
    session.execute(
        update(Run)
        .where(Run.status.in_(("pending", "running")))
        .values(status="interrupted", updated_at=now)
        .execution_options(synchronize_session=False)
    )
    return ids

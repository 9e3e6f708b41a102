"""A job run in the foreground by a CLI command (``monoloc map vocab``, ``monoloc map
calibrate``), recorded in the ``jobs`` table like the runner's: created, ``running``
with throttled progress, then ``done`` with its result, ``failed`` with the error or
``interrupted`` (Ctrl-C). Such a job is resumed by running the command again: every
kind is idempotent."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, TypeVar

from sqlalchemy.orm import Session, sessionmaker

from monoloc.server.jobs import store
from monoloc.server.jobs.progress import progress_recorder, update_job_now
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.records import JobRecord

T = TypeVar("T")

Progress = Callable[[int, int], None]


def run_recorded_job(
    session_factory: sessionmaker[Session],
    kind: str,
    *,
    map_id: int,
    params: Mapping[str, Any],
    started: str,
    describe_progress: Callable[[int, int], str],
    work: Callable[[JobRecord, Progress], T],
    result_of: Callable[[T], Mapping[str, Any]],
    progress: Progress | None = None,
) -> tuple[JobRecord, T]:
    """Record a job of ``kind`` on map ``map_id``, run ``work(job, report)`` and record
    how it ended; returns the final job row and what ``work`` returned.

    ``report(done, total)`` forwards to ``progress`` (e.g. a progress bar) and writes
    ``describe_progress(done, total)`` to the row. The job is done with
    ``result_of(value)``; any exception marks it failed (``interrupted`` for a
    KeyboardInterrupt) with its message, and is raised again.
    """
    with session_scope(session_factory) as session:
        job = store.create_job(session, kind, map_id=map_id, params=params, message="queued")
    update_job_now(session_factory, job.id, state="running", message=started)
    report = progress_recorder(session_factory, job.id, describe_progress, progress)
    try:
        value = work(job, report)
    except BaseException as exc:
        state = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
        update_job_now(session_factory, job.id, state=state, error=str(exc) or type(exc).__name__)
        raise
    job = update_job_now(
        session_factory, job.id, state="done", message="done", result=result_of(value)
    )
    return job, value

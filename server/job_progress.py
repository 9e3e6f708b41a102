"""Recording a long job's progress in its jobs row, for CLI-run jobs (the HTTP job runner
has its own): each update is its own short transaction, written at most twice a second."""

from __future__ import annotations

import time
from collections.abc import Callable

from sqlalchemy.orm import Session, sessionmaker

from monoloc.server.storage import jobs as jobs_repo
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.records import JobRecord


def update_job_now(factory: sessionmaker[Session], job_id: int, **fields) -> JobRecord:
    """Commit one change of a job row at once (state, progress, message, error, result)."""
    with session_scope(factory) as session:
        return jobs_repo.update_job(session, job_id, **fields)


def progress_recorder(
    factory: sessionmaker[Session],
    job_id: int,
    message: Callable[[int, int], str],
    forward: Callable[[int, int], None] | None = None,
    interval_s: float = 0.5,
) -> Callable[[int, int], None]:
    """A ``progress(done, total)`` callback that forwards every call (e.g. to a progress
    bar) and records progress + ``message(done, total)`` in the job row, throttled."""
    last = [0.0]

    def report(done: int, total: int) -> None:
        if forward is not None:
            forward(done, total)
        now = time.monotonic()
        if now - last[0] > interval_s or done == total:
            last[0] = now
            update_job_now(
                factory, job_id, progress=done / max(total, 1), message=message(done, total)
            )

    return report

"""Recording a job's progress in its row: each write is its own short transaction, at most
one every ``interval_s`` (twice a second by default). The runner's handlers write through
``JobContext.progress``, CLI-run jobs through :func:`progress_recorder`."""

from __future__ import annotations

import time
from collections.abc import Callable

from sqlalchemy.orm import Session, sessionmaker

from monoloc.server.jobs import store
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.records import JobRecord


def update_job_now(factory: sessionmaker[Session], job_id: int, **fields) -> JobRecord:
    """Commit one change of a job row at once (state, progress, message, error, result)."""
    with session_scope(factory) as session:
        return store.update_job(session, job_id, **fields)


class ProgressWriter:
    """Writes progress (0..1) and a message to one job row, skipping writes that come
    sooner than ``interval_s`` after the last one unless forced."""

    def __init__(
        self, factory: sessionmaker[Session], job_id: int, interval_s: float = 0.5
    ) -> None:
        self.factory = factory
        self.job_id = job_id
        self.interval_s = interval_s
        self._last_write = 0.0

    def write(self, fraction: float, message: str, *, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._last_write < self.interval_s:
            return
        self._last_write = now
        update_job_now(self.factory, self.job_id, progress=fraction, message=message)


def progress_recorder(
    factory: sessionmaker[Session],
    job_id: int,
    message: Callable[[int, int], str],
    forward: Callable[[int, int], None] | None = None,
    interval_s: float = 0.5,
) -> Callable[[int, int], None]:
    """A ``progress(done, total)`` callback that forwards every call (e.g. to a progress
    bar) and records progress + ``message(done, total)`` in the job row, throttled; the
    last step (``done == total``) is always recorded."""
    writer = ProgressWriter(factory, job_id, interval_s)

    def report(done: int, total: int) -> None:
        if forward is not None:
            forward(done, total)
        writer.write(done / max(total, 1), message(done, total), force=done == total)

    return report

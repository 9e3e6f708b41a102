"""Durable jobs: rows in the ``jobs`` table, run by a small thread pool.

A job is created (state ``queued``) in the same request that stores its input, then
submitted here. The runner moves it to ``running``, calls the handler registered for
its ``kind`` and records ``done`` (with the handler's result), ``failed`` (with the
error message) or ``interrupted`` (the handler honoured a stop request). Progress is
written to the row at most every ``progress_interval_s``.

After a restart the lifespan marks queued/running rows ``interrupted``
(``storage.jobs.mark_interrupted_jobs``); nothing is resumed behind the operator's back:
``POST /v1/jobs/{id}/resume`` re-queues one. Ingestion is idempotent by image hash, so a
resumed job adds only the frames that were missing. An ingestion job's upload stays in
``data_dir/uploads/<job id>`` until the job is done.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as wait_futures
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from monoloc.core.errors import ConflictError, MonolocError
from monoloc.server.api.archives import remove_tree
from monoloc.server.settings import Settings
from monoloc.server.storage import jobs as jobs_repo
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.records import JobRecord

log = logging.getLogger(__name__)


class JobInterruptedError(Exception):
    """Raised by a handler that stopped early because ``ctx.should_stop()`` said so."""


@dataclass
class JobContext:
    """What a handler gets: its job, the database, the registry, a stop flag, progress."""

    job: JobRecord
    sessions: sessionmaker[Session]
    registry: Any
    settings: Settings
    stop_event: threading.Event
    progress_interval_s: float = 0.5
    _last_write: float = field(default=0.0, init=False)

    def should_stop(self) -> bool:
        return self.stop_event.is_set()

    def progress(self, fraction: float, message: str = "", *, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._last_write < self.progress_interval_s:
            return
        self._last_write = now
        with session_scope(self.sessions) as session:
            jobs_repo.update_job(
                session,
                self.job.id,
                progress=min(1.0, max(0.0, float(fraction))),
                message=message,
            )

    def upload_dir(self) -> Path | None:
        """``data_dir/uploads/<job id>`` for jobs that came with an upload."""
        return upload_dir_of(self.job, self.settings)


JobHandler = Callable[[JobContext], Mapping[str, Any]]


def upload_dir_of(job: JobRecord, settings: Settings) -> Path | None:
    if not job.params.get("upload"):
        return None
    return Path(settings.data_dir) / "uploads" / str(job.id)


def public_message(text: str, settings: Settings) -> str:
    """An error message without the server's absolute upload paths."""
    uploads = str((Path(settings.data_dir) / "uploads").resolve()) + "/"
    return text.replace(uploads, "uploads/")


class JobRunner:
    """Runs queued jobs on ``settings.job_threads`` threads."""

    def __init__(
        self,
        sessions: sessionmaker[Session],
        registry: Any,
        settings: Settings,
        handlers: Mapping[str, JobHandler],
    ) -> None:
        self.sessions = sessions
        self.registry = registry
        self.settings = settings
        self.handlers = dict(handlers)
        self._executor: ThreadPoolExecutor | None = None
        self._stopping = threading.Event()
        self._stop_events: dict[int, threading.Event] = {}
        self._futures: dict[int, Future] = {}
        self._lock = threading.Lock()

    def start(self) -> None:
        self._stopping.clear()
        self._executor = ThreadPoolExecutor(
            max_workers=self.settings.job_threads, thread_name_prefix="monoloc-job"
        )

    def stop(self, timeout_s: float = 30.0) -> None:
        """Ask running jobs to stop (they end ``interrupted``) and wait up to ``timeout_s``."""
        self._stopping.set()
        with self._lock:
            for event in self._stop_events.values():
                event.set()
            futures = list(self._futures.values())
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
        wait_futures(futures, timeout=timeout_s)
        self._executor = None

    def active(self) -> list[int]:
        with self._lock:
            return sorted(self._futures)

    def submit(self, job_id: int) -> None:
        if self._executor is None or self._stopping.is_set():
            return  # stays queued; reported interrupted at the next start
        with self._lock:
            if job_id in self._futures:
                return
            self._stop_events[job_id] = threading.Event()
            self._futures[job_id] = self._executor.submit(self._run, job_id)

    def resume(self, job_id: int) -> JobRecord:
        """Re-queue an interrupted or failed job (ConflictError otherwise) and submit it."""
        with session_scope(self.sessions) as session:
            job = jobs_repo.get_job(session, job_id)
            if job.state not in ("interrupted", "failed"):
                raise ConflictError(
                    f"job {job_id} is {job.state}; only interrupted or failed jobs resume"
                )
            if job.kind not in self.handlers:
                raise ConflictError(f"job {job_id} is of kind {job.kind!r}, unknown here")
            upload = upload_dir_of(job, self.settings)
            if upload is not None and not upload.is_dir():
                raise ConflictError(f"the upload of job {job_id} is gone; upload the run again")
            job = jobs_repo.update_job(
                session, job_id, state="queued", progress=0.0, message="resumed"
            )
        self.submit(job_id)
        return job

    def cancel(self, job_id: int) -> JobRecord:
        """Stop a queued or running job; it ends ``interrupted`` and can be resumed."""
        with self._lock:
            event = self._stop_events.get(job_id)
        with session_scope(self.sessions) as session:
            job = jobs_repo.get_job(session, job_id)
            if job.state not in ("queued", "running"):
                raise ConflictError(f"job {job_id} is {job.state}; nothing to cancel")
            if event is None or job.state == "queued":
                job = jobs_repo.update_job(
                    session, job_id, state="interrupted", message="cancelled"
                )
        if event is not None:
            event.set()
        return job

    # ---- execution ------------------------------------------------------------------
    def _release(self, job_id: int) -> None:
        with self._lock:
            self._futures.pop(job_id, None)
            self._stop_events.pop(job_id, None)

    def _run(self, job_id: int) -> None:
        try:
            with session_scope(self.sessions) as session:
                job = jobs_repo.get_job(session, job_id)
                if job.state != "queued":
                    self._release(job_id)
                    return  # cancelled before it started
                job = jobs_repo.update_job(session, job_id, state="running", message="started")
            ctx = JobContext(
                job, self.sessions, self.registry, self.settings, self._stop_events[job_id]
            )
            changes = self._execute(ctx)
            # Forget the job before its final state is visible, so that a resume request
            # arriving right after that state can submit it again.
            self._release(job_id)
            with session_scope(self.sessions) as session:
                jobs_repo.update_job(session, job_id, **changes)
            upload = ctx.upload_dir()
            if changes["state"] == "done" and upload is not None:
                remove_tree(upload)
        except Exception:
            log.exception("job %s: bookkeeping failed", job_id)
        finally:
            self._release(job_id)

    def _execute(self, ctx: JobContext) -> dict[str, Any]:
        """Run the handler; returns the job's final state and what to record with it."""
        job = ctx.job
        handler = self.handlers.get(job.kind)
        try:
            if handler is None:
                raise ConflictError(f"no handler for jobs of kind {job.kind!r}")
            result = dict(handler(ctx))
        except JobInterruptedError as exc:
            return {"state": "interrupted", "message": str(exc) or "interrupted"}
        except MonolocError as exc:
            message = public_message(str(exc), self.settings)
            log.warning("job %s (%s) failed: %s", job.id, job.kind, message)
            return {"state": "failed", "error": message, "message": "failed"}
        except Exception as exc:  # a bug: keep the server alive, record it, log it
            log.exception("job %s (%s) crashed", job.id, job.kind)
            error = f"internal error: {type(exc).__name__}: {exc}"
            return {"state": "failed", "message": "failed", "error": error}
        return {"state": "done", "message": "done", "result": result}

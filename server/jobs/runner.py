"""The job queue: queued rows of the ``jobs`` table, run by a small thread pool.

A job is created (state ``queued``) in the same request that stores its input, then
submitted here. The runner moves it to ``running``, calls the handler registered for
its ``kind`` and records ``done`` (with the handler's result), ``failed`` (with the
error message) or ``interrupted`` (the handler honoured a stop request). Progress is
written to the row at most every ``JobContext.progress_interval_s``.

After a restart the lifespan marks queued/running rows ``interrupted``; :meth:`resume`
re-queues one (``monoloc.server.jobs.resume``). An ingestion job's upload stays in
``data_dir/uploads/<job id>`` until the job is done.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as wait_futures
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from monoloc.core.errors import ConflictError, MonolocError
from monoloc.server.jobs import store
from monoloc.server.jobs.context import JobContext, JobHandler, JobInterruptedError
from monoloc.server.jobs.resume import requeue_job
from monoloc.server.jobs.uploads import public_message, remove_tree
from monoloc.server.settings import Settings
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.records import JobRecord

log = logging.getLogger(__name__)


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
            job = requeue_job(session, job_id, kinds=self.handlers, settings=self.settings)
        self.submit(job_id)
        return job

    def cancel(self, job_id: int) -> JobRecord:
        """Stop a queued or running job; it ends ``interrupted`` and can be resumed."""
        with self._lock:
            event = self._stop_events.get(job_id)
        with session_scope(self.sessions) as session:
            job = store.get_job(session, job_id)
            if job.state not in ("queued", "running"):
                raise ConflictError(f"job {job_id} is {job.state}; nothing to cancel")
            if event is None or job.state == "queued":
                job = store.update_job(session, job_id, state="interrupted", message="cancelled")
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
                job = store.get_job(session, job_id)
                if job.state != "queued":
                    self._release(job_id)
                    return  # cancelled before it started
                job = store.update_job(session, job_id, state="running", message="started")
            ctx = JobContext(
                job, self.sessions, self.registry, self.settings, self._stop_events[job_id]
            )
            changes = self._execute(ctx)
            # Forget the job before its final state is visible, so that a resume request
            # arriving right after that state can submit it again.
            self._release(job_id)
            with session_scope(self.sessions) as session:
                store.update_job(session, job_id, **changes)
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

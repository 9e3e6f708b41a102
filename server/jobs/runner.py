"""The job queue: queued rows of the ``jobs`` table, taken as leases by any replica.

A job is created (state ``queued``) in the same request that stores its input; any
replica's runner claims it (``monoloc.server.jobs.lease``: ``FOR UPDATE SKIP LOCKED`` on
PostgreSQL), renews its lease every third of ``job_lease_s`` while the handler runs, and
records ``done`` (with the handler's result), ``failed`` (with the error message) or
``interrupted`` (cancelled) only while it still holds the lease. Progress is written
to the row at most every ``JobContext.progress_interval_s``.

A replica that dies stops renewing: once its lease expires another replica (or the
restarted process, at once for a dead process of the same host) takes the job over and
the idempotent handler resumes it. A graceful shutdown hands running jobs back to the
queue. :meth:`resume` re-queues an interrupted or failed job. An ingestion job's upload
stays in ``uploads_dir/<job id>`` (shared by the replicas) until the job is done.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as wait_futures
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from monoloc.core.errors import ConflictError, MonolocError
from monoloc.server.jobs import lease, store
from monoloc.server.jobs.context import JobContext, JobHandler, JobInterruptedError
from monoloc.server.jobs.resume import requeue_job
from monoloc.server.jobs.uploads import public_message, remove_tree
from monoloc.server.settings import Settings
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.records import JobRecord

log = logging.getLogger(__name__)


class JobRunner:
    """Claims and runs jobs on ``settings.job_threads`` threads, as one lease owner."""

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
        self.owner = lease.new_owner_id()
        self._executor: ThreadPoolExecutor | None = None
        self._stopping = threading.Event()
        self._wake = threading.Event()
        self._stop_events: dict[int, threading.Event] = {}
        self._futures: dict[int, Future] = {}
        self._lock = threading.Lock()
        self._poller: threading.Thread | None = None

    def start(self) -> None:
        self._stopping.clear()
        with session_scope(self.sessions) as session:
            dead = lease.expire_dead_local_leases(session)
        if dead:
            log.warning("jobs %s were held by a dead process of this host: taking over", dead)
        self._executor = ThreadPoolExecutor(
            max_workers=self.settings.job_threads, thread_name_prefix="monoloc-job"
        )
        self._poller = threading.Thread(target=self._poll, name="monoloc-job-leases", daemon=True)
        self._poller.start()

    def stop(self, timeout_s: float = 30.0) -> None:
        """Ask running jobs to stop, wait up to ``timeout_s``; they are handed back to the
        queue for another replica (or the next start) to take over."""
        self._stopping.set()
        self._wake.set()
        with self._lock:
            for event in self._stop_events.values():
                event.set()
            futures = list(self._futures.values())
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
        wait_futures(futures, timeout=timeout_s)
        if self._poller is not None:
            self._poller.join(timeout_s)
        self._executor = None

    def active(self) -> list[int]:
        with self._lock:
            return sorted(self._futures)

    def submit(self, job_id: int) -> None:
        """A job was queued: look for work now (this replica or another takes it)."""
        self._wake.set()

    # ---- leases ---------------------------------------------------------------------
    def _poll(self) -> None:
        lease_s = self.settings.job_lease_s
        next_renew = 0.0
        while not self._stopping.is_set():
            try:
                self._claim_while_free(lease_s)
                if time.monotonic() >= next_renew:
                    self._renew(lease_s)
                    next_renew = time.monotonic() + lease_s / 3
            except Exception:  # the database may be away for a moment
                log.exception("job leases: poll failed; retrying")
            self._wake.wait(min(self.settings.job_poll_s, lease_s / 3))
            self._wake.clear()

    def _claim_while_free(self, lease_s: float) -> None:
        while not self._stopping.is_set():
            with self._lock:
                if len(self._futures) >= self.settings.job_threads:
                    return
            with session_scope(self.sessions) as session:
                job = lease.claim_next_job(session, self.owner, lease_s, self.handlers)
            if job is None or self._executor is None:
                return
            with self._lock:
                self._stop_events[job.id] = threading.Event()
                self._futures[job.id] = self._executor.submit(self._run, job)

    def _renew(self, lease_s: float) -> None:
        with self._lock:
            held = list(self._stop_events.items())
        for job_id, stop in held:
            with session_scope(self.sessions) as session:
                ours = lease.renew_lease(session, job_id, self.owner, lease_s)
            if not ours:
                log.warning("job %s: lease lost (taken over or cancelled); stopping", job_id)
                stop.set()

    def resume(self, job_id: int) -> JobRecord:
        """Re-queue an interrupted or failed job (ConflictError otherwise) and submit it."""
        with session_scope(self.sessions) as session:
            job = requeue_job(session, job_id, kinds=self.handlers, settings=self.settings)
        self.submit(job_id)
        return job

    def cancel(self, job_id: int) -> JobRecord:
        """Stop a queued or running job (here or on another replica, whose lease renewal
        then fails); it ends ``interrupted`` and can be resumed."""
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

    def _run(self, job: JobRecord) -> None:
        job_id = job.id
        try:
            ctx = JobContext(
                job, self.sessions, self.registry, self.settings, self._stop_events[job_id]
            )
            changes = self._execute(ctx)
            # Forget the job before its final state is visible, so that a resume request
            # arriving right after that state can submit it again.
            self._release(job_id)
            with session_scope(self.sessions) as session:
                if not lease.holds_lease(session, job_id, self.owner):
                    log.warning("job %s: no longer ours; its outcome is not recorded", job_id)
                    return
                if changes["state"] == "interrupted" and self._stopping.is_set():
                    lease.hand_back(session, job_id, self.owner)
                    return
                store.update_job(session, job_id, **changes)
            upload = ctx.upload_dir()
            if changes["state"] == "done" and upload is not None:
                remove_tree(upload)
        except Exception:
            log.exception("job %s: bookkeeping failed", job_id)
        finally:
            self._release(job_id)
            self._wake.set()

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

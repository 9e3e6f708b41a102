"""Admission control: bounded lanes for localize, map writes, jobs and reads.

Every HTTP request of the API belongs to one *lane* (:func:`lane_of`): ``localize``
(``POST .../localize``), ``write`` (entry adds, deletes, re-tags, calibration and other
map edits), ``jobs`` (run uploads, job resumes) and ``read`` (every ``GET`` under
``/v1/``: most are cheap, but a whole map's poses or coverage costs as much as a write,
and any key may send them). A lane admits at most ``workers + queue_depth`` requests at
a time; one more is answered at once with 503 and ``Retry-After`` (whole seconds, HTTP's
unit; ``Retry-After-Ms`` gives the same wait to the millisecond; the requests shed in
one moment are given returns one service slot apart, :meth:`Lane.book_retry_ms`), before
its body is read, so it costs the server nothing (no upload spooled, no decode) and
memory stays bounded by the lanes' sizes whatever the offered load. Each lane has its
own worker threads (``workers``), which take the lane's queued computations themselves,
in arrival order: writes never queue behind a flood of frames and frames never behind an
upload, and a free worker starts the next frame at once, without a hand-over through the
event loop (which, busy reading requests under overload, waits for the GIL the workers
hold). ``/healthz``, ``/readyz``, ``/metrics``, the docs and the console's live event
stream (``.../vehicles/events``, open for 30 s and cheap) take no lane: they always
answer.

An admitted request carries a deadline: ``X-Request-Deadline-Ms`` (milliseconds the
client is willing to wait, counted from the server's receipt of the request), else the
lane's default. A request still queued at its deadline is answered then (503
``deadline_exceeded``), and one whose client disconnects leaves the queue as soon as the
close is seen (``client_disconnected``; a gone client never reads it): neither is
computed, and each frees its place in the lane at once. The body of an admitted request
must arrive in time too: a client that sends nothing for ``body_stall_s`` while its body is
due (a vehicle whose link dropped mid-upload, a slow-loris), or whose body is not complete
at its deadline (not for the jobs lane: a run archive may take longer to send than any
deadline), is answered 408 ``request_timeout`` and the connection closed
(``monoloc_admission_expired_total{reason="body_timeout"}``): without it, as many stalled
uploads as a lane has places would hold the lane shut for as long as their TCP
connections live. A WebSocket stream frame enters
the localize lane when its turn in its stream comes (:meth:`Admission.admitted`), with
the lane's default deadline counted from its arrival: a full lane drops it at once, as
it sheds an HTTP frame, so frames over HTTP and over the stream share the same bounded
queue (the stream also drops its own stale frames).

Counts go to :class:`monoloc.server.api.metrics.Metrics`: ``monoloc_admission_shed_total``,
``monoloc_admission_expired_total``; queue depth and running work are gauges read at
scrape time (:meth:`Admission.gauges`).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import contextvars
import json
import math
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, TypeVar

import anyio
from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from monoloc.core.errors import MonolocError

T = TypeVar("T")

DEADLINE_HEADER = b"x-request-deadline-ms"
LANES = ("localize", "write", "jobs", "read")

_LOCALIZE = re.compile(r"^/v1/maps/[^/]+/localize/?$")
_EVENTS = re.compile(r"^/v1/maps/[^/]+/vehicles/events/?$")
_JOBS = re.compile(r"^/v1/(maps/[^/]+/(runs|calibration/runs)(/.*)?|jobs(/.*)?)$")


class OverloadedError(MonolocError):
    """The request's lane is full; nothing was done. Retry after ``retry_after_s``."""

    http_status = 503
    code = "overloaded"

    def __init__(self, message: str, retry_after_s: int, retry_after_ms: int | None = None) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s
        # The same wait to the millisecond (``Retry-After-Ms``): HTTP's Retry-After counts
        # whole seconds, ten frames of a 10 Hz camera, while a lane drains in a fraction
        # of one.
        self.retry_after_ms = retry_after_s * 1000 if retry_after_ms is None else retry_after_ms

    @property
    def headers(self) -> dict[str, str]:
        """The answer's Retry-After headers."""
        return {"Retry-After": str(self.retry_after_s), "Retry-After-Ms": str(self.retry_after_ms)}


class DeadlineExceededError(OverloadedError):
    """The request's deadline passed before its turn came; it was not computed."""

    code = "deadline_exceeded"


class ClientDisconnectedError(OverloadedError):
    """The client went away before its request's turn came; it was not computed."""

    code = "client_disconnected"


@dataclass(frozen=True)
class LaneConfig:
    """One lane: concurrent computations, requests allowed to wait, default deadline."""

    workers: int
    queue_depth: int
    default_deadline_ms: int
    # whether the body must be complete by the deadline (False: only the stall timeout
    # bounds the upload, e.g. a run archive that takes longer than any deadline to send)
    body_by_deadline: bool = True
    # how far past the drain time the returns of shed requests are spread (s; at most
    # RETURN_SPREAD_SLOTS service slots, math.inf: the slots alone). Half the frame period
    # of a 10-Hz camera: a vehicle comes back on the frame nearest its wait, so a shed
    # costs it at most one frame more than the drain time does (Lane.book_retry_ms)
    return_spread_s: float = 0.05


def lane_of(method: str, path: str) -> str | None:
    """The lane of an HTTP request, or None (health, metrics, docs, OPTIONS: no lane)."""
    if method == "OPTIONS" or not path.startswith("/v1/"):
        return None
    if method in ("GET", "HEAD"):
        return None if _EVENTS.match(path) else "read"
    if _LOCALIZE.match(path):
        return "localize"
    if _JOBS.match(path):
        return "jobs"
    if path.startswith("/v1/"):
        return "write"
    return None


class BodyTimeoutError(HTTPException):
    """Raised from ``receive`` when an admitted request's body stops arriving. An
    HTTPException so that FastAPI's body parsing lets it through unchanged."""

    def __init__(self, message: str) -> None:
        # the rest of the body may still come: the connection cannot carry another request
        super().__init__(408, message, headers={"Connection": "close"})


def _timed_receive(
    receive: Receive, deadline_s: float, stall_s: float, on_timeout: Callable[[], None]
) -> Receive:
    """``receive`` that fails with :class:`BodyTimeoutError` (after ``on_timeout()``) when
    a body message does not come within ``stall_s`` or by ``deadline_s`` (monotonic). Once
    the body is complete, later calls (waiting for ``http.disconnect``) pass untimed."""
    complete = False

    async def timed() -> Message:
        nonlocal complete
        if complete:
            return await receive()
        left_s = deadline_s - time.monotonic()
        wait_s = min(stall_s, left_s)
        try:
            with anyio.fail_after(max(0.0, wait_s)):
                message = await receive()
        except TimeoutError:
            on_timeout()
            why = (
                f"nothing of it arrived for {stall_s:g} s"
                if stall_s <= left_s
                else "it was not complete at the request's deadline"
            )
            raise BodyTimeoutError(
                f"the request body did not arrive in time ({why}); send it again"
            ) from None
        if message["type"] != "http.request" or not message.get("more_body", False):
            complete = True
        return message

    return timed


class _DroppedError(Exception):
    """Raised into a queued job's future when its turn came too late (``reason``:
    ``deadline`` or ``disconnected``); it was not computed."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass(eq=False)
class _Job:
    fn: Callable[..., Any]
    args: tuple
    future: concurrent.futures.Future
    deadline_s: float  # monotonic
    ticket: Ticket | None
    context: contextvars.Context  # the submitter's, as anyio.to_thread would pass it

    def drop_reason(self) -> str | None:
        if time.monotonic() >= self.deadline_s:
            return "deadline"
        if self.ticket is not None and self.ticket.gone:
            return "disconnected"
        return None


class Lane:
    """Bounded admission (``workers + queue_depth`` requests inside) and the lane's own
    worker threads, which take queued computations in arrival order.

    The workers pull the next job themselves: a computation starts the moment a worker is
    free, without a round trip through the event loop (which, busy reading requests and
    holding the GIL, used to leave a worker idle for milliseconds between frames). A job
    whose deadline passed or whose client left while it waited is dropped by the worker
    when its turn comes, without being computed."""

    def __init__(self, name: str, config: LaneConfig) -> None:
        self.name = name
        self.config = config
        self.capacity = config.workers + config.queue_depth
        self._lock = threading.Lock()
        self._work_ready = threading.Condition(self._lock)
        self._queue: deque[_Job] = deque()
        self._threads: list[threading.Thread] = []
        self._stopping = False
        self._inside = 0
        self._running = 0
        self._service_s = 0.05  # moving average of one computation, for Retry-After
        # the latest return time (monotonic s) a shed answer gave; its own lock, which the
        # workers never take, so that a shed still waits on nothing the work holds
        self._last_return_s = -math.inf
        self._return_lock = threading.Lock()

    def try_enter(self) -> bool:
        """Take a place in the lane; False (shed) when it is full. A full lane is told
        without taking the lane's lock: the workers take it between computations, and a
        worker the OS preempted inside that section (a 2-core machine under 3-5x load)
        would hold every shed answer, and the event loop with it, until it runs again.
        The unlocked read may be a place behind (a slot freed a moment ago): a request
        is then shed that could have waited, never one admitted past the capacity."""
        if self._inside >= self.capacity:  # one int read, atomic under the GIL
            return False
        with self._lock:
            if self._inside >= self.capacity:
                return False
            self._inside += 1
            return True

    def leave(self) -> None:
        with self._lock:
            self._inside -= 1

    @property
    def inside(self) -> int:
        with self._lock:
            return self._inside

    @property
    def running(self) -> int:
        with self._lock:
            return self._running

    @property
    def waiting(self) -> int:
        """Jobs queued for a worker (not yet started)."""
        with self._lock:
            return len(self._queue)

    def retry_after_ms(self) -> int:
        """Milliseconds for the lane ahead to drain (every admitted request computed by the
        lane's workers at the recent service time), 1 ms to 60 s. Lock-free, like the shed
        decision it answers: the service time is one float, replaced whole by a worker."""
        drain_s = self.capacity * self._service_s / max(1, self.config.workers)
        return int(min(60_000, max(1, math.ceil(drain_s * 1000.0))))

    def retry_after_s(self) -> int:
        """The drain time in whole seconds (HTTP's unit), at least 1."""
        return whole_seconds(self.retry_after_ms())

    def record_service_s(self, elapsed_s: float) -> None:
        """Fold one computation's duration (s) into the service time the waits use."""
        with self._lock:
            self._service_s = 0.9 * self._service_s + 0.1 * elapsed_s

    def book_retry_ms(self, now_s: float | None = None) -> int:
        """The wait to give one shed request (ms, 1 ms to 60 s), booking its return: the
        drain time for the first, then one service slot (service time / workers) later
        for each next one shed before that return, up to the lane's ``return_spread_s``
        (at most ``RETURN_SPREAD_SLOTS`` slots) past the drain time, where the booking
        starts again at the drain time.

        Why: clients told the same wait all come back in the same few milliseconds, a
        burst far above capacity and then nothing while they wait (an idle lane); returns
        one slot apart arrive at the rate the lane serves. Why bounded, for vehicles: they
        come back on a frame (the one nearest the wait, ``client.localizer.FrameHold``),
        so a return booked further out does not spread them more, it holds frames the
        lane could have taken (booked over 60 slots, 1.2 s, the lane sat idle with places
        free while the vehicles held, 2026-12-02). ``now_s``: monotonic time of the shed
        (default: now)."""
        now_s = time.monotonic() if now_s is None else now_s
        slot_s = self._service_s / max(1, self.config.workers)
        first_s = now_s + self.capacity * slot_s
        spread_s = min(RETURN_SPREAD_SLOTS * slot_s, self.config.return_spread_s)
        with self._return_lock:
            at_s = max(first_s, self._last_return_s + slot_s)
            if at_s > first_s + spread_s + 0.5 * slot_s:  # half a slot: float sums
                at_s = first_s
            self._last_return_s = at_s
        # the microsecond's rounding first: a sum of slots is not exact in floats
        return int(min(60_000, max(1, math.ceil(round((at_s - now_s) * 1000.0, 3)))))

    def submit(
        self,
        fn: Callable[..., T],
        *args: Any,
        deadline_s: float = math.inf,
        ticket: Ticket | None = None,
    ) -> concurrent.futures.Future[T]:
        """Queue ``fn(*args)`` for the lane's workers (from any thread). The future fails
        with ``_DroppedError`` if the job's turn comes after ``deadline_s`` (monotonic) or
        after ``ticket``'s client left; cancelling it while queued drops the job."""
        future: concurrent.futures.Future[T] = concurrent.futures.Future()
        job = _Job(fn, args, future, deadline_s, ticket, contextvars.copy_context())
        with self._lock:
            if self._stopping:
                raise RuntimeError(f"the {self.name} lane is stopped")
            self._queue.append(job)
            self._threads = [t for t in self._threads if t.is_alive()]
            if len(self._threads) < self.config.workers:
                thread = threading.Thread(
                    target=self._work, name=f"monoloc-{self.name}", daemon=True
                )
                self._threads.append(thread)
                thread.start()
            self._work_ready.notify()
        return job.future

    def _next_job(self) -> _Job | None:
        """The next job to compute (None: the lane stops); drops the ones not wanted."""
        with self._lock:
            while True:
                while not self._queue and not self._stopping:
                    self._work_ready.wait()
                if not self._queue:
                    return None
                job = self._queue.popleft()
                if not job.future.set_running_or_notify_cancel():
                    continue  # cancelled while queued
                reason = job.drop_reason()
                if reason is not None:
                    job.future.set_exception(_DroppedError(reason))
                    continue
                self._running += 1
                return job

    def _work(self) -> None:
        while (job := self._next_job()) is not None:
            start = time.perf_counter()
            error: BaseException | None = None
            try:
                result = job.context.run(job.fn, *job.args)
            except BaseException as exc:  # noqa: BLE001 - handed to the waiting request
                error, result = exc, None
            # the lane's state counts this computation before its request is answered, so
            # what the lane says next (Retry-After) includes it
            elapsed = time.perf_counter() - start
            with self._lock:
                self._running -= 1
            self.record_service_s(elapsed)
            if error is not None:
                job.future.set_exception(error)
            else:
                job.future.set_result(result)
            del job, result, error  # drop the request's data before waiting for the next one

    def stop(self, timeout_s: float = 30.0) -> None:
        """Let the workers finish the queued jobs and end; the lane can start again."""
        with self._lock:
            self._stopping = True
            self._work_ready.notify_all()
            threads, self._threads = self._threads, []
        for thread in threads:
            thread.join(timeout_s)
        with self._lock:
            self._stopping = False

    def withdraw(self, future: concurrent.futures.Future, reason: str) -> bool:
        """Take a job out of the queue before its turn (its future fails with
        ``_DroppedError(reason)``, its data is freed); False if it already started."""
        with self._lock:
            job = next((job for job in self._queue if job.future is future), None)
            if job is None:
                return False
            self._queue.remove(job)
        try:
            future.set_exception(_DroppedError(reason))
        except concurrent.futures.InvalidStateError:
            pass  # its waiter cancelled it meanwhile
        return True

    async def compute(
        self,
        fn: Callable[..., T],
        *args: Any,
        deadline_s: float = math.inf,
        ticket: Ticket | None = None,
    ) -> T:
        """``fn(*args)`` computed by one of the lane's workers. Raises ``_DroppedError``
        if it was not computed: its deadline passed first (answered at the deadline, not
        when the queue reaches it), or its client left. A computation once started is
        never cut short; a cancelled caller withdraws its job or stops waiting for it."""
        future = self.submit(fn, *args, deadline_s=deadline_s, ticket=ticket)
        if ticket is not None:
            ticket.future = future
        waiting = asyncio.wrap_future(future)
        try:
            timeout_s = deadline_s - time.monotonic()
            if math.isinf(timeout_s):
                return await waiting
            try:
                return await asyncio.wait_for(asyncio.shield(waiting), max(0.0, timeout_s))
            except TimeoutError:
                self.withdraw(future, "deadline")
                return await waiting  # dropped, or already running: its answer is on its way
        except asyncio.CancelledError:
            self.withdraw(future, "cancelled")
            raise


# How far past the drain time shed requests' returns are spread, in service slots (at
# capacity, the requests the lane serves in that time), whatever the lane's
# ``return_spread_s``: clients that never wait keep booking returns, and the wrap keeps
# the waits of those that do from growing to the 60-s cap.
RETURN_SPREAD_SLOTS = 60


def whole_seconds(ms: int) -> int:
    """A wait in whole seconds (HTTP's Retry-After), 1 to 60."""
    return int(min(60, max(1, math.ceil(ms / 1000.0))))


@dataclass
class Ticket:
    """An admitted request: its lane, its deadline (monotonic s) and its ASGI receive."""

    lane: Lane
    deadline_s: float
    receive: Receive | None  # None: not an HTTP request (a stream frame), nothing to watch

    gone: bool = False
    future: concurrent.futures.Future | None = None  # its queued computation

    async def watch_disconnect(self) -> None:
        """Wait for the client to leave and remember it in ``gone``. Run it as a task once
        the request's body was read, while the request waits for its slot: the only
        message left is then ``http.disconnect``. Waiting on ``receive`` is also what
        resumes reading the socket (uvicorn pauses reading a connection whose body
        filled its buffer, and a paused socket never shows the client's close)."""
        message = await self.receive()
        if message.get("type") == "http.disconnect":
            self.gone = True
            if self.future is not None:  # still queued: leave the lane now
                self.lane.withdraw(self.future, "disconnected")


_ticket: contextvars.ContextVar[Ticket | None] = contextvars.ContextVar(
    "monoloc_admission_ticket", default=None
)


class Admission:
    """The lanes of one app, and the counters of what they turned away."""

    def __init__(self, configs: dict[str, LaneConfig], metrics, body_stall_s: float = 30.0) -> None:
        self.lanes = {name: Lane(name, configs[name]) for name in LANES}
        self.metrics = metrics
        self.body_stall_s = body_stall_s

    def shed(self, lane: Lane) -> OverloadedError:
        self.metrics.admission_shed.inc(lane.name)
        retry_ms = lane.book_retry_ms()
        return OverloadedError(
            f"the server is at capacity for {lane.name} requests "
            f"({lane.capacity} admitted); retry after the Retry-After seconds",
            whole_seconds(retry_ms),
            retry_ms,
        )

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        """Compute ``fn(*args)`` on the current request's lane, dropping the request
        first if its deadline passed or its client left while it waited. Outside a
        ticket (the WebSocket stream, start-up work) the localize lane's workers are used."""
        ticket = _ticket.get()
        if ticket is None:
            return await self.lanes["localize"].compute(fn, *args)
        lane = ticket.lane
        error: Exception | None = None
        async with anyio.create_task_group() as watchers:
            if not ticket.gone and ticket.receive is not None:
                watchers.start_soon(ticket.watch_disconnect)
            try:
                result = await lane.compute(fn, *args, deadline_s=ticket.deadline_s, ticket=ticket)
            except Exception as exc:  # raised outside the group, not as an ExceptionGroup
                error = exc
            finally:
                watchers.cancel_scope.cancel()
        if isinstance(error, _DroppedError):
            raise self._expired(lane, error.reason) from None
        if error is not None:
            raise error
        return result

    @contextlib.contextmanager
    def admitted(self, name: str, deadline_s: float) -> Iterator[bool]:
        """Admit work that is not an HTTP request (a stream frame) into lane ``name``, as
        the middleware admits a request: True inside (computations in the block run on
        the lane, dropped at ``deadline_s``, monotonic), False when the lane is full
        (counted as shed; do nothing)."""
        lane = self.lanes[name]
        if not lane.try_enter():
            self.metrics.admission_shed.inc(lane.name)
            yield False
            return
        token = _ticket.set(Ticket(lane, deadline_s, None))
        try:
            yield True
        finally:
            _ticket.reset(token)
            lane.leave()

    def _expired(self, lane: Lane, reason: str) -> OverloadedError:
        self.metrics.admission_expired.inc(lane.name, reason)
        if reason == "disconnected":
            return ClientDisconnectedError(
                "the client disconnected before its request was computed", 1
            )
        retry_ms = lane.book_retry_ms()
        return DeadlineExceededError(
            f"the request's deadline passed while it waited for a {lane.name} slot; "
            "it was not computed",
            whole_seconds(retry_ms),
            retry_ms,
        )

    def stop(self) -> None:
        """Stop the lanes' worker threads (at shutdown, once no request is in flight)."""
        for lane in self.lanes.values():
            lane.stop()

    def gauges(self) -> dict[str, dict[tuple[str, ...], float]]:
        """Per lane: requests waiting (admitted, not computing), computing, capacity."""
        waiting, running, capacity = {}, {}, {}
        for name, lane in self.lanes.items():
            busy = lane.running
            waiting[(name,)] = float(max(0, lane.inside - busy))
            running[(name,)] = float(busy)
            capacity[(name,)] = float(lane.capacity)
        return {"waiting": waiting, "running": running, "capacity": capacity}


def parse_deadline_ms(raw: bytes | None, default_ms: int) -> int:
    """The request's deadline budget in ms (header value, else ``default_ms``)."""
    if raw is None:
        return default_ms
    text = raw.decode("latin-1").strip()
    if not text.isdigit() or not 0 < int(text) <= 3_600_000:
        raise ValueError(
            f"X-Request-Deadline-Ms must be a whole number of milliseconds in 1..3600000, "
            f"got {text[:40]!r}"
        )
    return int(text)


async def _send_json(send: Send, status: int, body: dict, headers: list) -> None:
    payload = json.dumps(body).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(payload)).encode()),
                *headers,
            ],
        }
    )
    await send({"type": "http.response.body", "body": payload})


class AdmissionMiddleware:
    """Admits HTTP requests into their lane before anything reads their body."""

    def __init__(self, app: ASGIApp, admission: Admission) -> None:
        self.app = app
        self.admission = admission

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        name = None
        if scope["type"] == "http":
            name = lane_of(scope.get("method", ""), scope.get("path", ""))
        if name is None:
            await self.app(scope, receive, send)
            return
        lane = self.admission.lanes[name]
        headers = dict(scope.get("headers") or [])
        try:
            budget_ms = parse_deadline_ms(
                headers.get(DEADLINE_HEADER), lane.config.default_deadline_ms
            )
        except ValueError as exc:
            body = {"error": {"code": "bad_request", "message": str(exc)}}
            await _send_json(send, 400, body, [])
            return
        if not lane.try_enter():
            exc = self.admission.shed(lane)
            body = {"error": {"code": "overloaded", "message": str(exc)}}
            headers = [(k.lower().encode(), v.encode()) for k, v in exc.headers.items()]
            await _send_json(send, 503, body, headers)
            return
        deadline_s = time.monotonic() + budget_ms / 1e3
        token = _ticket.set(Ticket(lane, deadline_s, receive))
        expired = self.admission.metrics.admission_expired
        timed = _timed_receive(
            receive,
            deadline_s if lane.config.body_by_deadline else math.inf,
            self.admission.body_stall_s,
            lambda: expired.inc(lane.name, "body_timeout"),
        )
        try:
            await self.app(scope, timed, send)
        finally:
            _ticket.reset(token)
            lane.leave()


async def _overloaded(_request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, OverloadedError)
    body = {"error": {"code": exc.code, "message": str(exc)}}
    return JSONResponse(body, status_code=503, headers=exc.headers)


def install_admission(app: FastAPI, admission: Admission) -> None:
    """The lanes' middleware and the 503 + Retry-After answer of what they turn away."""
    app.add_exception_handler(OverloadedError, _overloaded)
    app.add_middleware(AdmissionMiddleware, admission=admission)

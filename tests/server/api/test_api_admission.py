"""Admission control over the real app: a full lane answers 503 + Retry-After at once
without reading the body, other lanes and health keep answering, a request whose
deadline passed or whose client left is not computed, /metrics counts it all."""

from __future__ import annotations

import asyncio
import contextvars
import math
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
from api_helpers import frame_png, free_port, make_settings, open_client

from monoloc.server.api.admission import Lane, LaneConfig, lane_of, parse_deadline_ms


def _localize(client, map_copy, sim_dataset, headers=None):
    return client.post(
        f"/v1/maps/{map_copy.map_id}/localize",
        files={"image": ("f.png", frame_png(sim_dataset, "01", 3), "image/png")},
        headers={**map_copy.keys.header("localize"), **(headers or {})},
    )


def _metric(client, map_copy, name: str) -> float:
    text = client.get("/metrics", headers=map_copy.keys.header("admin")).text
    total = 0.0
    for line in text.splitlines():
        if line.startswith(name):
            total += float(line.rsplit(" ", 1)[1])
    return total


@contextmanager
def _occupied(lane) -> Iterator[None]:
    """Every worker of ``lane`` busy with a job that waits for the block to end."""
    release = threading.Event()
    held = [lane.submit(release.wait) for _ in range(lane.config.workers)]
    deadline = time.monotonic() + 10
    while lane.running < lane.config.workers:
        assert time.monotonic() < deadline, "the lane's workers did not start"
        time.sleep(0.005)
    try:
        yield
    finally:
        release.set()
        for future in held:
            assert future.result(10) is True


def test_routes_fall_into_their_lanes():
    assert lane_of("POST", "/v1/maps/3/localize") == "localize"
    assert lane_of("POST", "/v1/maps/3/entries") == "write"
    assert lane_of("DELETE", "/v1/maps/3/entries/9") == "write"
    assert lane_of("PATCH", "/v1/maps/3/entries/9") == "write"
    assert lane_of("POST", "/v1/maps/3/runs") == "jobs"
    assert lane_of("POST", "/v1/jobs/4/resume") == "jobs"
    assert lane_of("GET", "/v1/maps/3/entries") == "read"
    assert lane_of("GET", "/v1/maps/3/vehicles/events") is None
    assert lane_of("GET", "/healthz") is None and lane_of("GET", "/readyz") is None
    assert parse_deadline_ms(None, 2000) == 2000 and parse_deadline_ms(b" 150 ", 2000) == 150
    for bad in (b"0", b"-5", b"1.5", b"soon", b"99999999"):
        with pytest.raises(ValueError, match="X-Request-Deadline-Ms"):
            parse_deadline_ms(bad, 2000)


def test_lane_workers_take_queued_jobs_themselves_and_drop_expired_ones():
    # No event loop here at all: a worker that finishes a job takes the next one itself.
    lane = Lane("localize", LaneConfig(workers=1, queue_depth=2, default_deadline_ms=1000))
    try:
        done: list[str] = []
        release = threading.Event()
        first = lane.submit(release.wait)
        second = lane.submit(done.append, "second")
        late = lane.submit(done.append, "late", deadline_s=time.monotonic() + 0.05)
        time.sleep(0.1)  # the late job's deadline passes while the worker is busy
        assert (lane.running, lane.waiting) == (1, 2)
        release.set()
        assert first.result(5) is True and second.result(5) is None
        assert late.exception(5).reason == "deadline"  # dropped unrun
        assert done == ["second"] and lane.waiting == 0
        # a job withdrawn from the queue (its client left) is never run
        release.clear()
        busy = lane.submit(release.wait)
        while lane.running < 1:
            time.sleep(0.005)
        withdrawn = lane.submit(done.append, "withdrawn")
        assert lane.withdraw(withdrawn, "disconnected") and lane.waiting == 0
        assert withdrawn.exception(5).reason == "disconnected"
        release.set()
        assert busy.result(5) is True and not lane.withdraw(busy, "disconnected")
        assert done == ["second"]
        # the job runs in the submitter's context (contextvars), as anyio's threads did
        request_id = contextvars.ContextVar("request_id", default=None)
        request_id.set("frame-7")
        assert lane.submit(request_id.get).result(5) == "frame-7"
    finally:
        lane.stop()
    assert lane.submit(done.append, "after a restart").result(5) is None
    lane.stop()
    assert done[-1] == "after a restart"


def test_retry_after_is_the_lanes_drain_time_to_the_millisecond():
    # 2 workers, 2 waiting: a full lane drains in 4 service times over 2 workers
    lane = Lane("localize", LaneConfig(workers=2, queue_depth=2, default_deadline_ms=1000))
    try:
        fresh_ms = lane.retry_after_ms()
        assert 0 < fresh_ms < 1000 and lane.retry_after_s() == 1  # HTTP's whole seconds
        for _ in range(3):  # computations of 0.3 s raise the service time it is based on
            lane.submit(time.sleep, 0.3).result(5)
        assert lane.retry_after_ms() > fresh_ms + 100
    finally:
        lane.stop()


def test_a_full_lane_sheds_at_once_while_writes_and_health_answer(map_copy, sim_dataset):
    settings = make_settings(map_copy.data_dir, worker_threads=1, localize_queue_depth=1)
    with open_client(settings) as client:
        assert _localize(client, map_copy, sim_dataset).status_code == 200
        lane = client.app.state.monoloc.admission.lanes["localize"]
        assert lane.capacity == 2
        assert lane.try_enter() and lane.try_enter()  # the lane is full
        try:
            start = time.perf_counter()
            shed = _localize(client, map_copy, sim_dataset)
            elapsed_s = time.perf_counter() - start
            assert shed.status_code == 503, shed.text
            assert shed.json()["error"]["code"] == "overloaded"
            assert int(shed.headers["Retry-After"]) >= 1
            # the lane's drain time to the millisecond (the full lane computes nothing, so
            # it is what the lane says now), and Retry-After is it in whole seconds
            wait_ms = int(shed.headers["Retry-After-Ms"])
            assert wait_ms == lane.retry_after_ms()
            assert int(shed.headers["Retry-After"]) == max(1, math.ceil(wait_ms / 1000))
            assert elapsed_s < 1.0
            # writes have their own lane; health never queues
            write = map_copy.keys.header("write")
            entries = client.get(f"/v1/maps/{map_copy.map_id}/entries", headers=write).json()
            entry_id = entries["items"][0]["id"]
            r = client.patch(
                f"/v1/maps/{map_copy.map_id}/entries/{entry_id}",
                json={"tags": ["night"]},
                headers=write,
            )
            assert r.status_code == 200, r.text
            assert client.get("/healthz").status_code == 200
            assert client.get("/readyz").status_code == 200
            bad = _localize(client, map_copy, sim_dataset, {"X-Request-Deadline-Ms": "soon"})
            assert bad.status_code == 400 and "X-Request-Deadline-Ms" in bad.text
        finally:
            lane.leave()
            lane.leave()
        assert _localize(client, map_copy, sim_dataset).status_code == 200
        assert _metric(client, map_copy, 'monoloc_admission_shed_total{lane="localize"}') == 1
        assert _metric(client, map_copy, 'monoloc_admission_capacity{lane="localize"}') == 2


def test_a_request_whose_deadline_passes_in_the_queue_is_not_computed(map_copy, sim_dataset):
    settings = make_settings(map_copy.data_dir, worker_threads=1)
    with open_client(settings) as client:
        lane = client.app.state.monoloc.admission.lanes["localize"]
        computed = "monoloc_localize_stage_duration_seconds_count"
        before = _metric(client, map_copy, computed)
        with _occupied(lane):  # the one worker is busy
            start = time.perf_counter()
            r = _localize(client, map_copy, sim_dataset, {"X-Request-Deadline-Ms": "300"})
            waited_s = time.perf_counter() - start
            assert lane.waiting == 0  # the expired job left the queue with its answer
        assert r.status_code == 503 and r.json()["error"]["code"] == "deadline_exceeded"
        assert "Retry-After" in r.headers
        assert 0.3 <= waited_s < 3.0
        assert _metric(client, map_copy, computed) == before  # no stage ran
        expired = 'monoloc_admission_expired_total{lane="localize",reason="deadline"}'
        assert _metric(client, map_copy, expired) == 1
        ok = _localize(client, map_copy, sim_dataset, {"X-Request-Deadline-Ms": "5000"})
        assert ok.status_code == 200
        assert _metric(client, map_copy, computed) > before


@contextmanager
def _uvicorn(app) -> Iterator[tuple[int, asyncio.AbstractEventLoop]]:
    """``app`` on a real uvicorn in a thread, on a loop the test can schedule onto."""
    import uvicorn

    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_until_complete, args=(server.serve(),))
    thread.start()
    deadline = time.monotonic() + 60
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.02)
    try:
        yield port, loop
    finally:
        server.should_exit = True
        thread.join(30)
        loop.close()


def _multipart_request(port: int, map_id: int, key: str, png: bytes) -> bytes:
    boundary = "monolocboundary"
    body = (
        (
            f'--{boundary}\r\nContent-Disposition: form-data; name="image"; filename="f.png"\r\n'
            f"Content-Type: image/png\r\n\r\n"
        ).encode()
        + png
        + f"\r\n--{boundary}--\r\n".encode()
    )
    head = (
        f"POST /v1/maps/{map_id}/localize HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
        f"X-API-Key: {key}\r\nContent-Type: multipart/form-data; boundary={boundary}\r\n"
        f"Content-Length: {len(body)}\r\n\r\n"
    ).encode()
    return head + body


# This failed about 1 run in 2 while the server peeked at `receive` for the close: uvicorn
# pauses reading a connection whose body filled its buffer, so the close went unseen.
# The server now waits on `receive` while the request waits for its slot (6/6 passes).
def test_a_client_that_left_is_not_computed_and_a_full_lane_reads_no_body(map_copy, sim_dataset):
    from monoloc.server.api.app import create_app

    app = create_app(make_settings(map_copy.data_dir, worker_threads=1, localize_queue_depth=1))
    with _uvicorn(app) as (port, loop):
        state = app.state.monoloc
        lane = state.admission.lanes["localize"]
        release = threading.Event()
        held = lane.submit(release.wait)
        while lane.running < 1:  # the one worker is busy
            time.sleep(0.005)
        request = _multipart_request(
            port, map_copy.map_id, map_copy.keys.localize, frame_png(sim_dataset, "01", 3)
        )
        with socket.create_connection(("127.0.0.1", port)) as gone:
            gone.sendall(request)
            deadline = time.monotonic() + 10
            while lane.waiting < 1:  # parsed, queued for the busy worker
                assert time.monotonic() < deadline
                time.sleep(0.01)
            # Fill the lane's last place; a request announcing 100 MB is then refused
            # before a byte of its body is sent.
            assert lane.try_enter() and not lane.try_enter()
            try:
                with socket.create_connection(("127.0.0.1", port)) as flood:
                    flood.sendall(
                        f"POST /v1/maps/{map_copy.map_id}/localize HTTP/1.1\r\nHost: x\r\n"
                        f"X-API-Key: {map_copy.keys.localize}\r\nContent-Length: 100000000\r\n"
                        "Content-Type: multipart/form-data; boundary=b\r\n\r\n".encode()
                    )
                    flood.settimeout(5)
                    answer = flood.recv(4096).decode()
            finally:
                lane.leave()
            assert answer.startswith("HTTP/1.1 503") and "retry-after" in answer.lower()
        # The first client has gone: its request leaves the queue (and the lane) as soon
        # as the server sees the close, while the worker is still busy.
        deadline = time.monotonic() + 10
        while lane.waiting or lane.inside:
            assert time.monotonic() < deadline, "the gone client's request stayed queued"
            time.sleep(0.01)
        assert not held.done()
        release.set()
        assert held.result(10) is True
        deadline = time.monotonic() + 10
        while lane.inside:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        assert state.metrics.admission_expired.value("localize", "disconnected") == 1
        rendered = list(state.metrics.localize_stages.render())
        assert not any(line.startswith("monoloc_localize_stage") for line in rendered[2:])


def _answer(
    sock: socket.socket, timeout_s: float, await_close: bool = True
) -> tuple[str, float, bool]:
    """(the server's whole answer, seconds until it came, whether the server then closed;
    without ``await_close`` False at once: a kept-alive connection would hold the check for
    ``timeout_s``)."""
    sock.settimeout(timeout_s)
    start = time.monotonic()
    data = sock.recv(65536)
    waited_s = time.monotonic() - start
    while b"\r\n\r\n" not in data and data:
        data += sock.recv(65536)
    head, _, body = data.partition(b"\r\n\r\n")
    length = next(
        (
            int(line.split(b":")[1])
            for line in head.lower().split(b"\r\n")
            if line.startswith(b"content-length:")
        ),
        0,
    )
    while len(body) < length:
        more = sock.recv(65536)
        if not more:
            break
        body += more
    data = head + b"\r\n\r\n" + body
    if not await_close:
        return data.decode("latin-1"), waited_s, False
    try:
        closed = sock.recv(65536) == b""
    except (TimeoutError, ConnectionResetError):
        closed = False
    return data.decode("latin-1"), waited_s, closed


def test_a_stalled_upload_is_answered_408_at_its_deadline_and_frees_the_lane(map_copy, sim_dataset):
    from monoloc.server.api.app import create_app

    settings = make_settings(map_copy.data_dir, worker_threads=1, localize_queue_depth=0)
    app = create_app(settings)
    with _uvicorn(app) as (port, _loop):
        state = app.state.monoloc
        lane = state.admission.lanes["localize"]
        png = frame_png(sim_dataset, "01", 3)
        request = _multipart_request(port, map_copy.map_id, map_copy.keys.localize, png)
        head, body = request.split(b"\r\n\r\n", 1)
        head = head.replace(b"\r\nX-API-Key", b"\r\nX-Request-Deadline-Ms: 600\r\nX-API-Key")
        with socket.create_connection(("127.0.0.1", port)) as stalled:
            # a vehicle whose link drops mid-upload: half its frame, then nothing
            stalled.sendall(head + b"\r\n\r\n" + body[: len(body) // 2])
            deadline = time.monotonic() + 5
            while lane.inside < 1:
                assert time.monotonic() < deadline, "the stalled request was not admitted"
                time.sleep(0.01)
            with socket.create_connection(("127.0.0.1", port)) as other:
                other.sendall(request)
                shed, _, _ = _answer(other, 5, await_close=False)
            assert shed.startswith("HTTP/1.1 503")  # its one place is taken meanwhile
            answer, waited_s, closed = _answer(stalled, 10)
        assert answer.startswith("HTTP/1.1 408"), answer
        assert "request_timeout" in answer and "deadline" in answer
        assert "connection: close" in answer.lower() and closed
        assert waited_s < 3.0
        deadline = time.monotonic() + 5
        while lane.inside:
            assert time.monotonic() < deadline, "the stalled request kept its place"
            time.sleep(0.01)
        assert state.metrics.admission_expired.value("localize", "body_timeout") == 1
        with socket.create_connection(("127.0.0.1", port)) as after:
            after.sendall(request)
            served, _, _ = _answer(after, 60, await_close=False)
        assert served.startswith("HTTP/1.1 200"), served[:200]


def test_an_upload_that_stops_arriving_is_cut_one_that_trickles_is_not(map_copy):
    from monoloc.server.api.app import create_app

    app = create_app(make_settings(map_copy.data_dir, body_stall_timeout_s=0.5))
    write = map_copy.keys.header("write")
    with _uvicorn(app) as (port, _loop):
        state = app.state.monoloc
        import httpx

        entries = httpx.get(
            f"http://127.0.0.1:{port}/v1/maps/{map_copy.map_id}/entries", headers=write
        ).json()
        entry_id = entries["items"][0]["id"]
        body = b'{"tags": ["night", "trickled"]}'
        head = (
            f"PATCH /v1/maps/{map_copy.map_id}/entries/{entry_id} HTTP/1.1\r\nHost: x\r\n"
            f"X-API-Key: {write['X-API-Key']}\r\nContent-Type: application/json\r\n"
            f"Content-Length: {len(body)}\r\n\r\n"
        ).encode()
        # 0.2 s between chunks, 1.6 s in all: longer than the stall timeout, never idle for it
        with socket.create_connection(("127.0.0.1", port)) as slow:
            slow.sendall(head)
            for i in range(0, len(body), 4):
                time.sleep(0.2)
                slow.sendall(body[i : i + 4])
            answer, _, _ = _answer(slow, 10, await_close=False)
        assert answer.startswith("HTTP/1.1 200"), answer
        assert '"trickled"' in answer
        # the same write whose client goes silent after a few bytes
        with socket.create_connection(("127.0.0.1", port)) as silent:
            silent.sendall(head + body[:5])
            answer, waited_s, closed = _answer(silent, 10)
        assert answer.startswith("HTTP/1.1 408"), answer
        assert "nothing of it arrived for 0.5 s" in answer and closed
        assert 0.4 <= waited_s < 3.0
        assert state.metrics.admission_expired.value("write", "body_timeout") == 1
        assert state.admission.lanes["write"].inside == 0
        tags = httpx.get(
            f"http://127.0.0.1:{port}/v1/maps/{map_copy.map_id}/entries/{entry_id}",
            headers=write,
        ).json()["tags"]
        assert sorted(tags) == ["night", "trickled"]  # the cut write changed nothing


def _shed_scope(path: str = "/v1/maps/1/localize") -> dict:
    return {"type": "http", "method": "POST", "path": path, "headers": []}


def test_a_shed_decision_waits_on_nothing_the_work_holds():
    """A full lane's 503 is decided and sent in one step of the middleware: no await that
    suspends (no queue, no event-loop round trip), no body read, and not even the lane's
    lock, which a worker holds between computations (one the OS preempted there, on a
    loaded 2-core machine, used to hold every shed answer and the event loop with it)."""
    from monoloc.server.api.admission import LANES, Admission, AdmissionMiddleware
    from monoloc.server.api.metrics import Metrics

    config = LaneConfig(workers=1, queue_depth=0, default_deadline_ms=1000)
    admission = Admission(dict.fromkeys(LANES, config), Metrics())
    lane = admission.lanes["localize"]

    async def app(scope, receive, send):  # the work: never reached by a shed request
        raise AssertionError("a shed request reached the route")

    middleware = AdmissionMiddleware(app, admission)
    sent: list[dict] = []
    outcome: dict[str, object] = {}

    async def receive():
        raise AssertionError("a shed request's body was read")

    async def send(message):
        sent.append(message)

    def shed_once() -> None:
        step = middleware(_shed_scope(), receive, send)
        try:
            step.send(None)
        except StopIteration:
            outcome["done_in_one_step"] = True
        else:
            step.close()
            outcome["done_in_one_step"] = False

    try:
        with _occupied(lane):
            assert lane.try_enter() is True  # the request the busy worker computes
            assert lane.try_enter() is False  # full
            with lane._lock:  # a worker inside its critical section
                shedder = threading.Thread(target=shed_once, daemon=True)
                shedder.start()
                shedder.join(5.0)
                answered_under_the_lock = not shedder.is_alive()
            shedder.join(5.0)
            lane.leave()
    finally:
        admission.stop()
    assert answered_under_the_lock, "the shed answer waited for the lane's lock"
    assert outcome == {"done_in_one_step": True}
    start, body = sent
    assert start["status"] == 503
    headers = dict(start["headers"])
    assert int(headers[b"retry-after"]) >= 1 and int(headers[b"retry-after-ms"]) >= 1
    assert b"overloaded" in body["body"]
    assert admission.metrics.admission_shed.value("localize") == 1

"""Replica processes (`monoloc serve`) on one real PostgreSQL: a write on one is seen by
localize on the other within 1 s; writes on one while the other serves frames leave
every replica's index equal to the database; SIGKILL of the replica running an
ingestion job: the other takes it over and finishes it, no duplicate, no loss; the
docker/nginx.conf front (on loopback) spreads frames over both replicas."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import socket
import threading
import time

import httpx
import pytest
from fleet_helpers import (
    create_map,
    find_nginx,
    free_port,
    loopback_nginx_conf,
    upload_run,
    wait_job,
)
from sqlalchemy import create_engine, func, select

from monoloc.server.storage.models import Entry, Job

FRAME = 7


def _frame(street, seq: str, i: int) -> bytes:
    return (street / "sequences" / seq / "image_0" / f"{i:06d}.png").read_bytes()


def _localize(fleet, replica, street, headers=None) -> httpx.Response:
    return httpx.post(
        f"{replica.url}/v1/maps/{fleet.map_id}/localize",
        files={"image": ("f.png", _frame(street, "01", FRAME), "image/png")},
        data={"k": "10", "seed": "1"},
        headers={**fleet.headers("localize"), **(headers or {})},
        timeout=30,
    )


def _replica_state(fleet, replica, map_id=None) -> dict:
    r = httpx.get(
        f"{replica.url}/v1/maps/{map_id or fleet.map_id}/replica",
        headers=fleet.headers("admin"),
        timeout=30,
    )
    assert r.status_code == 200, r.text
    return r.json()


def _retrieved(answer: dict) -> set[int]:
    return {int(r["entry_id"]) for r in answer["retrieved"]}


def test_a_write_on_one_replica_reaches_localize_on_the_other_within_1s(fleet, street):
    a, b = fleet.replicas
    before = _localize(fleet, b, street)
    assert before.status_code == 200, before.text
    victim = sorted(_retrieved(before.json()))[0]
    r = httpx.delete(
        f"{a.url}/v1/maps/{fleet.map_id}/entries/{victim}",
        headers=fleet.headers("write"),
        timeout=30,
    )
    assert r.status_code == 204, r.text
    version = int(r.headers["X-Map-Version"])
    written = time.monotonic()
    # without asking: b's sync applies the change log by itself
    while _replica_state(fleet, b)["replica"]["map_version"] < version:
        assert time.monotonic() - written < 1.0, "replica b did not catch up within 1 s"
        time.sleep(0.02)
    after = _localize(fleet, b, street)
    assert after.status_code == 200 and after.json()["map_version"] >= version
    assert victim not in _retrieved(after.json())
    # read-your-writes: a version no replica can reach yet is refused, not answered stale
    stale = _localize(fleet, b, street, {"X-Min-Map-Version": str(version + 1000)})
    assert stale.status_code == 503 and stale.json()["error"]["code"] == "stale_replica"
    assert "Retry-After" in stale.headers
    fresh = _localize(fleet, b, street, {"X-Min-Map-Version": str(version)})
    assert fresh.status_code == 200 and fresh.json()["map_version"] >= version


def test_writes_on_one_replica_while_the_other_localizes_leave_every_index_equal_to_the_db(
    fleet, street
):
    a, b = fleet.replicas
    entries = httpx.get(
        f"{a.url}/v1/maps/{fleet.map_id}/entries?limit=1000",
        headers=fleet.headers("write"),
        timeout=30,
    ).json()["items"]
    ids = [e["id"] for e in entries]
    assert len(ids) >= 20
    answers: list[int] = []
    stop = threading.Event()

    def vehicle() -> None:
        while not stop.is_set():
            answers.append(_localize(fleet, b, street).status_code)

    thread = threading.Thread(target=vehicle)
    thread.start()
    try:
        for i, entry_id in enumerate(ids[:20]):  # 15 re-tags, 5 deletes, interleaved
            url = f"{a.url}/v1/maps/{fleet.map_id}/entries/{entry_id}"
            if i % 4 == 3:
                r = httpx.delete(url, headers=fleet.headers("write"), timeout=30)
                assert r.status_code == 204, r.text
            else:
                r = httpx.patch(
                    url,
                    json={"tags": ["night", f"w{i}"]},
                    headers=fleet.headers("write"),
                    timeout=30,
                )
                assert r.status_code == 200, r.text
    finally:
        stop.set()
        thread.join(60)
    assert answers and set(answers) == {200}
    deadline = time.monotonic() + 60  # a bound, not a latency (the test above has that)
    for replica in fleet.replicas:
        while not (state := _replica_state(fleet, replica))["in_sync"]:
            assert time.monotonic() < deadline, state
            time.sleep(0.05)
        assert state["replica"]["entries"] == len(ids) - 5


def test_sigkill_of_the_replica_running_an_ingestion_the_other_finishes_it(fleet, street):
    a, b = fleet.replicas
    map_id = _new_map(fleet, street)
    job_id = _upload(fleet, a, map_id, street)
    engine = create_engine(fleet.database_url)
    try:
        holder = _wait_for_progress(engine, job_id)
        pid = int(holder.split(":")[1])
        victim = next(r for r in fleet.replicas if r.process and r.process.pid == pid)
        os.kill(pid, signal.SIGKILL)
        victim.process.wait(10)
        survivor = b if victim is a else a
        job = wait_job(survivor.url, job_id, fleet.headers("admin"))
        assert job["state"] == "done", job
        with engine.connect() as connection:
            row = connection.execute(
                select(Job.attempts, Job.lease_owner).where(Job.id == job_id)
            ).one()
            n, distinct = connection.execute(
                select(
                    func.count(Entry.id), func.count(func.distinct(Entry.source_image_hash))
                ).where(Entry.map_id == map_id)
            ).one()
        assert row.attempts == 2 and row.lease_owner != holder
        assert n == distinct  # no duplicate
        skipped = job["result"]["skip_reasons"]
        frames = len(list((street / "sequences" / "01" / "image_0").iterdir()))
        assert n + skipped.get("too_few_points", 0) == frames  # no loss
        victim.start()  # back, it catches up from the database
        victim.wait_ready()
        for replica in fleet.replicas:
            assert _replica_state(fleet, replica, map_id)["in_sync"]
    finally:
        engine.dispose()


def _new_map(fleet, street) -> int:
    return create_map(fleet.replicas[0].url, fleet.keys, "second", street)


def _upload(fleet, replica, map_id, street) -> int:
    return upload_run(replica.url, fleet.keys, map_id, street, "01")


def _wait_for_progress(engine, job_id: int, timeout_s: float = 60.0) -> str:
    """The lease owner of the job once it has committed some entries."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with engine.connect() as connection:
            state, owner, progress = connection.execute(
                select(Job.state, Job.lease_owner, Job.progress).where(Job.id == job_id)
            ).one()
        assert state in ("queued", "running"), state
        if state == "running" and owner and progress > 0:
            return owner
        time.sleep(0.01)
    raise AssertionError("the ingestion made no progress")


@contextlib.contextmanager
def _nginx_front(fleet, tmp_path, localize_limit: int | None = None):
    """docker/nginx.conf on loopback before the fleet's replicas (its localize admission
    at ``localize_limit`` frames per replica when given); yields its url."""
    import subprocess

    nginx = find_nginx()
    if nginx is None:
        pytest.fail("nginx is not installed (make test installs Debian's nginx-light)")
    for kind in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi"):
        (tmp_path / kind).mkdir()
    port = free_port()
    conf = loopback_nginx_conf(tmp_path, [r.port for r in fleet.replicas], port)
    if localize_limit is not None:  # frames let in to each replica
        text, n = re.subn(r"max_conns=\d+", f"max_conns={localize_limit}", conf.read_text())
        assert n == len(fleet.replicas)
        conf.write_text(text)
    subprocess.run([nginx, "-p", str(tmp_path), "-c", str(conf)], check=True)
    try:
        front = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"{front}/readyz", timeout=10).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, (tmp_path / "error.log").read_text()
            time.sleep(0.05)
        yield front
    finally:
        subprocess.run([nginx, "-p", str(tmp_path), "-c", str(conf), "-s", "quit"], check=False)


def test_nginx_in_front_spreads_frames_over_both_replicas(fleet, street, tmp_path):
    with _nginx_front(fleet, tmp_path) as front, httpx.Client(timeout=30) as client:
        for _ in range(8):
            r = client.post(
                f"{front}/v1/maps/{fleet.map_id}/localize",
                files={"image": ("f.png", _frame(street, "01", FRAME), "image/png")},
                headers=fleet.headers("localize"),
            )
            assert r.status_code == 200, r.text
    log = (tmp_path / "access.log").read_text()
    for replica in fleet.replicas:
        assert f"upstream=127.0.0.1:{replica.port}" in log, log


def test_nginx_sheds_frames_beyond_its_localize_admission_and_not_a_slow_upload(
    fleet, street, tmp_path
):
    """The admission counts frames whole: a vehicle whose upload is still arriving holds
    no slot (the next frame is served), while frames sent together beyond the one slot of
    each replica are answered 503 by nginx itself, in the replicas' error shape with
    Retry-After / Retry-After-Ms, and never proxied."""
    from concurrent.futures import ThreadPoolExecutor

    path = f"/v1/maps/{fleet.map_id}/localize"
    frame = _frame(street, "01", FRAME)

    def localize(front: str) -> httpx.Response:
        files = {"image": ("f.png", frame, "image/png")}
        return httpx.post(f"{front}{path}", files=files, headers=fleet.headers("localize"))

    with _nginx_front(fleet, tmp_path, localize_limit=1) as front:
        port = int(front.rsplit(":", 1)[1])
        with socket.create_connection(("127.0.0.1", port), timeout=10) as slow:
            key = fleet.headers("localize")["X-API-Key"]
            slow.sendall(
                f"POST {path} HTTP/1.1\r\nHost: x\r\nX-API-Key: {key}\r\n"
                "Content-Type: multipart/form-data; boundary=b\r\n"
                "Content-Length: 100000\r\n\r\n--b\r\n".encode()
            )
            time.sleep(0.3)  # nginx is reading its body
            served = localize(front)
            assert served.status_code == 200, served.text
            with ThreadPoolExecutor(8) as pool:
                together = list(pool.map(localize, [front] * 8))
    codes = sorted(r.status_code for r in together)
    assert codes.count(200) >= 1 and codes.count(503) >= 1 and set(codes) == {200, 503}, codes
    for shed in (r for r in together if r.status_code == 503):
        assert shed.json()["error"]["code"] == "overloaded"
        assert shed.headers["retry-after"] == "1" and int(shed.headers["retry-after-ms"]) > 0
    log = [line for line in (tmp_path / "access.log").read_text().splitlines() if path in line]
    shed_lines = [line for line in log if " 503 " in line]
    assert len(shed_lines) == codes.count(503), log
    # never proxied: nginx found no replica with room (no address tried)
    assert all("upstream=monoloc_localize " in line for line in shed_lines), shed_lines


def _vehicles(fleet, replica) -> list[dict]:
    r = httpx.get(
        f"{replica.url}/v1/maps/{fleet.map_id}/vehicles",
        headers=fleet.headers("localize"),
        timeout=30,
    )
    assert r.status_code == 200, r.text
    return r.json()["vehicles"]


def test_the_live_board_of_one_replica_shows_vehicles_streaming_to_the_other(fleet, street):
    from monoloc.client.api import FrameStream

    a, b = fleet.replicas
    stream = FrameStream(b.url, fleet.keys["localize"], fleet.map_id, timeout_s=60)
    try:
        for seq in range(3):
            stream.send(seq, 0.1 * seq, _frame(street, "01", FRAME + seq), seed=1)
            assert "hypotheses" in stream.receive()
        (on_b,) = [v for v in _vehicles(fleet, b) if v["connected"]]
        deadline = time.monotonic() + 10
        while True:  # the relay sends within a quarter of a second
            seen = [v for v in _vehicles(fleet, a) if v["replica"] == on_b["replica"]]
            if seen and seen[0]["frames"] == 3:
                break
            assert time.monotonic() < deadline, _vehicles(fleet, a)
            time.sleep(0.1)
        (vehicle,) = seen
        assert vehicle["connected"] and vehicle["name"] == "localize"
        assert vehicle["vehicle_id"] == on_b["vehicle_id"]
        assert vehicle["last_seq"] == 2 and vehicle["estimate"] is not None
    finally:
        stream.close()
    deadline = time.monotonic() + 10
    while any(v["connected"] for v in _vehicles(fleet, a) if v["replica"] == on_b["replica"]):
        assert time.monotonic() < deadline, "a still shows the closed stream connected"
        time.sleep(0.1)

"""bench/load.py's overload measurement over real loopback sockets: its bare asyncio 503
server (the floor) answers the generator's frame requests on keep-alive connections,
and an open-loop phase's summary carries the shed answers' latency and the floor's."""

from __future__ import annotations

import asyncio

from bench import load


def test_an_open_loop_phase_against_the_floor_reports_shed_and_floor_latencies():
    frames = [b"\x89PNG\r\n\x1a\n" + bytes(200_000), b"\x89PNG\r\n\x1a\n" + bytes(50_000)]
    with load.floor_server() as floor_url:
        phase = load.open_loop_http(
            [floor_url], 1, frames, 3, 20.0, 1.0, False, [], floor_url=floor_url
        )
        part = asyncio.run(phase)
    run = load.summarise([part])
    # 3 vehicles x 20 Hz for 1 s, every frame answered 503 by the floor server
    assert 55 <= run["offered"] <= 61, run["offered"]
    assert run["shed"] == run["offered"] and run["served_per_s"] == 0.0
    assert run["failed_no_answer"] == 0 and run["errors_5xx"] == 0
    assert 0.0 < run["shed_p50_ms"] <= run["shed_p99_ms"] <= run["shed_max_ms"]
    assert 0.0 <= run["shed_within_50ms"] <= 1.0
    # the floor's own vehicle, at the per-vehicle rate
    assert 18 <= run["floor_answers"] <= 21, run["floor_answers"]
    assert 0.0 < run["floor_p50_ms"] <= run["floor_p99_ms"] <= run["floor_max_ms"]


def test_an_honouring_vehicle_sends_one_frame_at_a_time_as_the_library_does():
    """While its frame is unanswered (a slow server, 0.3 s), an honouring vehicle does not
    send the next one (BUSY), as HttpLocalizer, which waits for each answer; a vehicle
    sending every frame has both in flight."""
    answer = b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\n\r\n{}"

    async def slow(reader, writer):
        try:
            while True:
                head = await reader.readuntil(b"\r\n\r\n")
                length = next(
                    int(line.split(b":")[1])
                    for line in head.split(b"\r\n")
                    if line.lower().startswith(b"content-length:")
                )
                await reader.readexactly(length)
                await asyncio.sleep(0.3)
                writer.write(answer)
        except (asyncio.IncompleteReadError, ConnectionError):
            writer.close()

    async def run(honour: bool) -> list[int]:
        server = await asyncio.start_server(slow, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        requests = load.FrameRequests(1, [b"\x89PNG" + bytes(1000)], None)
        link = load.VehicleLink(f"http://127.0.0.1:{port}", 4, 5.0, honour_retry_after=honour)
        first = asyncio.ensure_future(link.post(requests, 0))
        await asyncio.sleep(0.1)
        second = await link.post(requests, 0)  # taken while the first is unanswered
        statuses = [(await first)[0], second[0], (await link.post(requests, 0))[0]]
        link.close()
        server.close()
        await server.wait_closed()
        return statuses

    assert asyncio.run(run(True)) == [200, load.BUSY, 200]
    assert asyncio.run(run(False)) == [200, 200, 200]


def test_the_nginx_front_runs_docker_nginx_conf_before_the_upstreams(tmp_path):
    """``--front nginx``: docker/nginx.conf made to run before given upstreams (in each
    upstream block, the admission's per-replica limit set) starts, and the generator's
    frames pass through it to the floor server (which answers each 503) with no failure;
    nginx's own shedding is tests/fleet/test_replicas.py's."""
    with load.floor_server() as floor_url:
        text = load.front_config([floor_url, floor_url], 8080, 3, tmp_path)
        assert text.count("max_conns=3 ") == 2 and "max_conns=4" not in text
        # every upstream block (the localize admission's and the other routes') names both
        assert text.count(floor_url[7:]) == 4
        assert "monoloc-1" not in text and "listen 127.0.0.1:8080;" in text
        with load.nginx_front([floor_url], 1, tmp_path / "nginx") as (front_url, pids):
            assert len(pids) >= 2  # master and worker, counted as the server's
            phase = load.open_loop_http(
                [front_url], 1, [b"\x89PNG\r\n\x1a\n" + bytes(100_000)], 8, 20.0, 1.0, False, []
            )
            run = load.summarise([asyncio.run(phase)])
    assert run["failed_no_answer"] == 0 and run["errors_5xx"] == 0
    assert run["shed"] == run["offered"] > 100

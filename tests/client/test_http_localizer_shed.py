"""The vehicle's HTTP localizer under a shedding server: a 503 frame is a dropped frame,
not a retry; the Retry-After window is honoured; the counts say what happened."""

from __future__ import annotations

import httpx
import pytest

from monoloc.client.api import MonolocClient, ServerError
from monoloc.client.localizer import HttpLocalizer

HYP = {
    "pose": {"x_m": 1.0, "y_m": 2.0, "yaw_rad": 0.1},
    "entry_pose": {"x_m": 1.5, "y_m": 2.0, "yaw_rad": 0.0},
    "e_vlad": 0.4,
    "n_inliers": 50,
}


class FakeClock:
    def __init__(self) -> None:
        self.now_s = 100.0

    def __call__(self) -> float:
        return self.now_s


def scripted(statuses: list[int], seen: list[httpx.Request]):
    """A transport answering the given statuses in turn (503s with Retry-After: 2)."""

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        status = statuses[len(seen) - 1]
        if status == 503:
            body = {"error": {"code": "overloaded", "message": "at capacity"}}
            return httpx.Response(503, json=body, headers={"Retry-After": "2"})
        if status == 200:
            return httpx.Response(200, json={"hypotheses": [HYP], "map_version": 4})
        return httpx.Response(status, json={"error": {"code": "x", "message": "boom"}})

    return httpx.MockTransport(handler)


def test_a_shed_frame_is_dropped_once_and_the_retry_after_window_is_honoured():
    seen: list[httpx.Request] = []
    clock = FakeClock()
    client = MonolocClient("http://fake", "mlk_t", retries=3, transport=scripted([503, 200], seen))
    with client:
        localizer = HttpLocalizer(client, 7, deadline_ms=150, clock=clock)
        first = localizer.localize(b"png")
        assert first.dropped and first.raw["reason"] == "shed" and len(first.hypotheses) == 0
        assert len(seen) == 1  # no retry of a stale frame, despite retries=3
        assert seen[0].headers["X-Request-Deadline-Ms"] == "150"
        for i in range(1, 20):  # 10 Hz for 1.9 s: inside the 2 s window, nothing is sent
            clock.now_s = 100.0 + 0.1 * i
            held = localizer.localize(b"png")
            assert held.dropped and held.raw["reason"] == "held"
        assert len(seen) == 1
        clock.now_s = 102.0
        answer = localizer.localize(b"png")
    assert not answer.dropped and len(answer.hypotheses) == 1 and answer.map_version == 4
    counts = localizer.counts
    assert (counts.sent, counts.answered, counts.shed, counts.held) == (2, 1, 1, 19)


def test_the_millisecond_retry_after_is_honoured_before_the_whole_seconds():
    seen: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        if len(seen) == 1:
            body = {"error": {"code": "overloaded", "message": "at capacity"}}
            headers = {"Retry-After": "1", "Retry-After-Ms": "250"}
            return httpx.Response(503, json=body, headers=headers)
        return httpx.Response(200, json={"hypotheses": [HYP], "map_version": 4})

    clock = FakeClock()
    with MonolocClient("http://fake", "mlk_t", transport=httpx.MockTransport(handler)) as client:
        localizer = HttpLocalizer(client, 7, clock=clock)
        assert localizer.localize(b"png").raw["reason"] == "shed"
        clock.now_s = 100.2  # inside the 250 ms
        assert localizer.localize(b"png").raw["reason"] == "held"
        clock.now_s = 100.3  # past them, though inside the whole second
        answer = localizer.localize(b"png")
    assert not answer.dropped and len(seen) == 2
    assert (localizer.counts.shed, localizer.counts.held) == (1, 1)


def test_other_errors_still_raise():
    seen: list[httpx.Request] = []
    client = MonolocClient("http://fake", "mlk_t", retries=0, transport=scripted([422], seen))
    with client, pytest.raises(ServerError, match="boom"):
        HttpLocalizer(client, 7).localize(b"png")


def test_the_client_reports_the_servers_retry_after_when_it_gives_up():
    seen: list[httpx.Request] = []
    client = MonolocClient(
        "http://fake",
        "mlk_t",
        retries=1,
        backoff_s=0,
        max_backoff_s=0,
        transport=scripted([503, 503], seen),
    )
    with client, pytest.raises(ServerError) as caught:
        client.localize(7, b"png", min_map_version=12)
    assert caught.value.status_code == 503 and caught.value.retry_after_s == 2.0
    assert len(seen) == 2 and seen[0].headers["X-Min-Map-Version"] == "12"

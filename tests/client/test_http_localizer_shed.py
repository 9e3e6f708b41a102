"""The vehicle's HTTP localizer under a shedding server: a 503 frame is a dropped frame,
not a retry; the Retry-After window is honoured; the counts say what happened."""

from __future__ import annotations

import httpx
import numpy as np
import pytest

from monoloc.client.api import RETRY_JITTER, MonolocClient, ServerError
from monoloc.client.localizer import FrameHold, HttpLocalizer

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
    # the hold is the server's 2 s lengthened by the jitter drawn from the vehicle's rng
    hold_s = 2.0 * (1.0 + RETRY_JITTER * np.random.default_rng(3).random())
    with client:
        localizer = HttpLocalizer(
            client, 7, deadline_ms=150, clock=clock, rng=np.random.default_rng(3)
        )
        first = localizer.localize(b"png")
        assert first.dropped and first.raw["reason"] == "shed" and len(first.hypotheses) == 0
        assert len(seen) == 1  # no retry of a stale frame, despite retries=3
        assert seen[0].headers["X-Request-Deadline-Ms"] == "150"
        held_frames = 0
        # 100 Hz through the window: nothing is sent before the frame nearest its end
        while (at_s := 100.0 + 0.01 * (held_frames + 1)) < 100.0 + hold_s - 0.005:
            clock.now_s = at_s
            held = localizer.localize(b"png")
            assert held.dropped and held.raw["reason"] == "held"
            held_frames += 1
        assert len(seen) == 1 and held_frames >= 199  # never before the server's 2 s
        clock.now_s = 100.0 + 0.01 * (held_frames + 1)  # within half a frame of the end
        answer = localizer.localize(b"png")
    assert not answer.dropped and len(answer.hypotheses) == 1 and answer.map_version == 4
    counts = localizer.counts
    assert (counts.sent, counts.answered, counts.shed, counts.held) == (2, 1, 1, held_frames)


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
        clock.now_s = 100.1  # at 10 Hz, inside the 250 ms and not the frame nearest them
        assert localizer.localize(b"png").raw["reason"] == "held"
        clock.now_s = 100.0 + 0.25 * (1 + RETRY_JITTER)  # past them and the jitter, though
        # inside the whole second
        answer = localizer.localize(b"png")
    assert not answer.dropped and len(seen) == 2
    assert (localizer.counts.shed, localizer.counts.held) == (1, 1)


def test_vehicles_told_the_same_wait_do_not_all_come_back_at_once():
    """20 vehicles shed in the same moment with the same wait (a proxy's fixed Retry-After,
    or a server that does not spread its waits): each holds for the wait plus its own
    jitter, so they come back spread over a quarter of the wait, none before it."""
    clock = FakeClock()

    def handler(request: httpx.Request) -> httpx.Response:
        if clock.now_s == 100.0:
            body = {"error": {"code": "overloaded", "message": "at capacity"}}
            return httpx.Response(503, json=body, headers={"Retry-After-Ms": "400"})
        return httpx.Response(200, json={"hypotheses": [HYP], "map_version": 4})

    back_s: dict[int, float] = {}
    with MonolocClient("http://fake", "mlk_t", transport=httpx.MockTransport(handler)) as client:
        fleet = [
            HttpLocalizer(client, 7, clock=clock, rng=np.random.default_rng(v)) for v in range(20)
        ]
        for vehicle in fleet:
            assert vehicle.localize(b"png").raw["reason"] == "shed"
        for tick in range(1, 120):  # every vehicle tries every 5 ms for 0.6 s
            clock.now_s = 100.0 + 0.005 * tick
            for v, vehicle in enumerate(fleet):
                if v not in back_s and not vehicle.localize(b"png").dropped:
                    back_s[v] = clock.now_s
    returns_ms = sorted(round(1000 * (t - 100.0)) for t in back_s.values())
    assert len(returns_ms) == 20 and returns_ms[0] >= 400  # all back, none too early
    assert returns_ms[-1] <= 400 * (1 + RETRY_JITTER) + 5
    assert returns_ms[-1] - returns_ms[0] >= 50, returns_ms  # spread, not one burst
    most_in_one_tick = max(returns_ms.count(t) for t in returns_ms)
    assert most_in_one_tick <= 4, returns_ms


def test_the_retry_wait_of_the_client_is_jittered_never_shortened(monkeypatch):
    """MonolocClient's own retries (uploads, map calls) wait the server's Retry-After plus
    up to RETRY_JITTER of it, drawn from the injected rng: two clients seeded alike wait
    alike, two seeded apart do not."""
    slept: list[float] = []
    monkeypatch.setattr("monoloc.client.api.time.sleep", slept.append)

    def waits(seed: int) -> list[float]:
        seen: list[httpx.Request] = []
        transport = scripted([503, 503, 503, 200], seen)
        rng = np.random.default_rng(seed)
        with MonolocClient("http://fake", "mlk_t", retries=3, transport=transport, rng=rng) as c:
            c.localize(7, b"png")
        taken = slept[-3:]
        return taken

    first, again, other = waits(1), waits(1), waits(2)
    assert first == again and first != other
    assert all(2.0 <= w <= 2.0 * (1 + RETRY_JITTER) for w in first + other)
    assert len(set(first)) == 3


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


def _frames_sent_after_a_shed(wait_ms: int, seed: int) -> list[int]:
    """A 10-Hz vehicle whose first frame (at 100.0 s) is shed with ``wait_ms``: the
    frames (1, 2, ...) it sends over the next 0.5 s, every one answered."""
    clock, seen = FakeClock(), []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(clock.now_s)
        if len(seen) == 1:
            body = {"error": {"code": "overloaded", "message": "at capacity"}}
            return httpx.Response(503, json=body, headers={"Retry-After-Ms": str(wait_ms)})
        return httpx.Response(200, json={"hypotheses": [HYP], "map_version": 4})

    with MonolocClient("http://fake", "mlk_t", transport=httpx.MockTransport(handler)) as client:
        vehicle = HttpLocalizer(client, 7, clock=clock, rng=np.random.default_rng(seed))
        sent = []
        for frame in range(6):
            clock.now_s = 100.0 + 0.1 * frame
            if not vehicle.localize(b"png").dropped:
                sent.append(frame)
    assert vehicle.counts.shed == 1 and vehicle.counts.held == 5 - len(sent)
    return sent


def test_a_10_hz_vehicle_comes_back_on_the_frame_nearest_the_wait():
    """Told 110 ms (a lane's drain time a little over one frame period), the vehicle
    sends its very next frame, 10-38 ms before the wait with its jitter is over, instead
    of holding it and coming back 90 ms late; told 160 or 260 ms, it holds one or two
    frames, and the frame it comes back on is never more than half a period early."""
    for seed in range(8):  # jitter draws across [0, 1)
        assert _frames_sent_after_a_shed(110, seed) == [1, 2, 3, 4, 5]
        assert _frames_sent_after_a_shed(160, seed) == [2, 3, 4, 5]
        assert _frames_sent_after_a_shed(260, seed) == [3, 4, 5]


def test_the_frame_hold_takes_the_vehicles_own_frame_period():
    """FrameHold's rule on its own: a frame is held while the next one is nearer the
    return (shed at 10.0 s, wait 0.4 s lengthened by the rng's jitter), the period being
    the last interval between frames: at 20, 10 and 5 Hz the vehicle comes back within
    half its own period of the return, and sends every frame after."""
    return_s = 10.0 + 0.4 * (1.0 + RETRY_JITTER * np.random.default_rng(5).random())
    for period_s in (0.05, 0.1, 0.2):
        hold = FrameHold(np.random.default_rng(5))
        assert hold.send(10.0 - period_s) and hold.send(10.0)
        hold.shed(10.0, 0.4)
        frames_s = [10.0 + period_s * k for k in range(1, 20)]
        first_s = next(t for t in frames_s if hold.send(t))
        assert all(hold.send(t) for t in frames_s if t > first_s)  # the hold is over
        assert return_s - period_s / 2 <= first_s < return_s + period_s / 2, period_s

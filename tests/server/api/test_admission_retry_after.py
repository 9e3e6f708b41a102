"""The waits a full lane gives the requests it sheds: not one drain time for all (the
vehicles would come back together, a burst far above capacity, then leave the lane idle)
but returns booked one service slot apart, bounded (by the lane's return_spread_s, at
most RETURN_SPREAD_SLOTS slots), over the real app too."""

from __future__ import annotations

import dataclasses
import math
import time

from monoloc.server.api.admission import RETURN_SPREAD_SLOTS, Lane, LaneConfig


def _lane(workers: int = 2, queue_depth: int = 2, return_spread_s: float = math.inf) -> Lane:
    """A lane with 40-ms computations (a slot of 20 ms over 2 workers); by default its
    returns spread over the slots alone (RETURN_SPREAD_SLOTS), not a time."""
    config = LaneConfig(workers, queue_depth, 1000, return_spread_s=return_spread_s)
    lane = Lane("localize", config)
    lane._service_s = 0.040
    return lane


def test_the_default_spread_is_half_a_10_hz_frame_period():
    """Vehicles come back on a frame (the nearest to their wait): returns booked past half
    a frame period would hold frames the lane could take. With 20-ms slots the waits
    run from the drain time (80 ms) to 50 ms past it, then start again."""
    lane = Lane("localize", LaneConfig(2, 2, default_deadline_ms=1000))
    lane._service_s = 0.040
    assert lane.config.return_spread_s == 0.05
    waits = [lane.book_retry_ms(now_s=50.0) for _ in range(9)]
    assert waits == [80, 100, 120, 80, 100, 120, 80, 100, 120]
    # a slower lane (50-ms slots): the spread holds one slot, never more than 50 ms
    lane._service_s = 0.100
    waits = [lane.book_retry_ms(now_s=60.0) for _ in range(4)]
    assert waits == [200, 250, 200, 250]


def test_requests_shed_in_one_moment_are_given_returns_one_slot_apart():
    lane = _lane()
    drain_ms = lane.retry_after_ms()  # 4 places x 20 ms
    assert drain_ms == 80
    waits = [lane.book_retry_ms(now_s=50.0) for _ in range(20)]
    # the first is told the drain time, each next one slot (20 ms) later: 20 vehicles come
    # back over 380 ms, at the rate the lane serves them, not in the same millisecond
    assert waits == [80 + 20 * k for k in range(20)]


def test_a_shed_after_the_booked_returns_passed_is_told_the_drain_time_again():
    lane = _lane()
    for _ in range(10):
        lane.book_retry_ms(now_s=50.0)  # returns booked until 50.0 + 0.26 s
    assert lane.book_retry_ms(now_s=50.1) == 180  # behind the booked ones, at 50.28
    assert lane.book_retry_ms(now_s=60.0) == 80  # long after: nobody ahead


def test_the_spread_is_bounded_and_starts_again_at_the_drain_time():
    """Clients that never wait keep being shed; their bookings must not push the waits
    of the others to the 60-s cap: past RETURN_SPREAD_SLOTS slots they wrap around."""
    lane = _lane()
    n = 3 * (RETURN_SPREAD_SLOTS + 1)
    waits = [lane.book_retry_ms(now_s=50.0) for _ in range(n)]
    longest_ms = 80 + 20 * RETURN_SPREAD_SLOTS
    assert min(waits) == 80 and max(waits) == longest_ms
    # each wait of the window given as often (3 times), none outside it
    assert sorted(waits) == sorted(3 * [80 + 20 * k for k in range(RETURN_SPREAD_SLOTS + 1)])


def test_the_slot_follows_the_lanes_service_time():
    lane = Lane("localize", LaneConfig(workers=1, queue_depth=1, default_deadline_ms=1000))
    try:
        for _ in range(20):  # computations of 60 ms: the moving average approaches them
            lane.submit(time.sleep, 0.06).result(5)
        first, second = lane.book_retry_ms(now_s=1.0), lane.book_retry_ms(now_s=1.0)
        slot_ms = 1000 * lane._service_s
        assert 45 < slot_ms < 80
        assert abs(first - 2 * slot_ms) <= 1 and abs(second - first - slot_ms) <= 1
    finally:
        lane.stop()


def test_the_apps_shed_answers_carry_spread_waits(fresh):
    client, keys = fresh
    lane = client.app.state.monoloc.admission.lanes["localize"]
    lane._service_s = 1.0  # a slot of 0.5 s: far longer than a request takes here
    # slots that long are past the default 50-ms spread: spread over the slots alone
    lane.config = dataclasses.replace(lane.config, return_spread_s=math.inf)
    for _ in range(lane.capacity):
        assert lane.try_enter()
    try:
        sent_s, answered_s, answers = [], [], []
        for _ in range(6):
            sent_s.append(time.monotonic())
            answers.append(
                client.post(
                    "/v1/maps/1/localize",
                    files={"image": ("f.png", b"\x89PNG" + bytes(1000), "image/png")},
                    headers={"X-API-Key": keys.localize},
                )
            )
            answered_s.append(time.monotonic())
    finally:
        for _ in range(lane.capacity):
            lane.leave()
    assert [a.status_code for a in answers] == [503] * 6
    waits_ms = [int(a.headers["Retry-After-Ms"]) for a in answers]
    assert waits_ms[0] <= 2000  # the drain time: 4 places x 0.5 s
    # A wait counts from the server's receipt, somewhere between the request's sending and
    # its answer (a loaded machine may hold a request for a second in between): the
    # booked returns are at least one slot (500 ms) apart, however the requests went.
    latest_ms = [1000 * t + w for t, w in zip(answered_s, waits_ms, strict=True)]
    earliest_ms = [1000 * t + w for t, w in zip(sent_s, waits_ms, strict=True)]
    widest_gaps_ms = [b - a for a, b in zip(earliest_ms, latest_ms[1:], strict=False)]
    assert all(gap >= 495 for gap in widest_gaps_ms), (waits_ms, widest_gaps_ms)
    assert max(waits_ms) - min(waits_ms) >= 1000, waits_ms  # later ones were told later
    assert [int(a.headers["Retry-After"]) for a in answers] == [
        max(1, -(-w // 1000)) for w in waits_ms
    ]

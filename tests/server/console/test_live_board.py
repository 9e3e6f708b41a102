"""The board of live vehicles: estimate, hypotheses, frame rate and latency on an
injected clock."""

from __future__ import annotations

import pytest

from monoloc.server.api.console.live import BoardConfig, PlanarEstimate, VehicleBoard


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _answer(seq, x_m):
    pose = {"x_m": x_m, "y_m": 1.0, "yaw_rad": 0.5}
    hypothesis = {"entry_id": 7, "n_inliers": 40, "pose": pose}
    return {"seq": seq, "t": seq * 0.1, "hypotheses": [hypothesis]}


def test_rate_latency_and_estimate_from_the_answers():
    clock = Clock()
    board = VehicleBoard(BoardConfig(rate_window_s=5.0, forget_after_s=10.0), clock)
    feed = board.connect(map_id=1, name="car")
    other = board.connect(map_id=2, name="bus")
    for seq in range(11):  # 10 Hz, 30 ms from arrival to answer
        clock.now = 100.0 + seq * 0.1
        received = clock.now
        clock.now += 0.03
        feed.report(_answer(seq, x_m=seq * 1.5), received)
    (car,) = board.snapshot(1)["vehicles"]
    assert car["frames"] == 11 and car["last_seq"] == 10
    assert car["frame_rate_hz"] == pytest.approx(10.0)
    assert car["latency_ms_p50"] == pytest.approx(30.0)
    assert car["estimate"] == {"x_m": 15.0, "y_m": 1.0, "yaw_rad": 0.5}
    assert car["estimate_source"] == "best hypothesis"
    assert car["hypotheses"] == [
        {"entry_id": 7, "n_inliers": 40, "x_m": 15.0, "y_m": 1.0, "yaw_rad": 0.5}
    ]
    assert [v["name"] for v in board.snapshot(2)["vehicles"]] == ["bus"]
    assert other.vehicle_id != feed.vehicle_id


def test_the_vehicle_prior_is_its_estimate_and_skips_are_counted():
    clock = Clock()
    board = VehicleBoard(clock=clock)
    feed = board.connect(1, "car")
    version = board.snapshot(1)["version"]
    feed.report(_answer(0, 3.0), clock.now, prior=PlanarEstimate(2.0, 0.5, None))
    feed.report({"seq": 1, "dropped": True, "reason": "stale"}, clock.now)
    feed.report({"seq": 2, "error": {"code": "invalid_input", "message": "x"}}, clock.now)
    snap = board.snapshot(1)
    (car,) = snap["vehicles"]
    assert snap["version"] == version + 3
    assert car["estimate"] == {"x_m": 2.0, "y_m": 0.5, "yaw_rad": None}
    assert car["estimate_source"] == "vehicle prior"
    assert (car["frames"], car["dropped"], car["errors"]) == (1, 1, 1)


def test_a_closed_stream_is_forgotten_after_a_while():
    clock = Clock()
    board = VehicleBoard(BoardConfig(forget_after_s=10.0), clock)
    feed = board.connect(1, "car")
    feed.close()
    clock.now += 5.0
    (car,) = board.snapshot(1)["vehicles"]
    assert car["connected"] is False
    clock.now += 6.0
    assert board.snapshot(1)["vehicles"] == []

"""bench/shed_model.py: the server's own Lane on simulated time. Vehicles given booked
waits send about one shed frame per served one, a quarter of what the drain time for
all lets through at 5x, with the lane kept as busy; a stall lengthens a computation."""

from __future__ import annotations

import pytest

from bench import shed_model


def test_booked_waits_shed_far_less_and_keep_the_lane_busy():
    cfg = shed_model.ModelConfig(seconds=15.0)
    before = shed_model.simulate("before", 5.0, cfg)
    booked = shed_model.simulate("booked+jitter", 5.0, cfg)
    assert before["vehicles"] == booked["vehicles"] == 23
    # the drain time (90 ms) is shorter than a frame period: nothing held, 4x shed
    assert before["held"] == 0 and before["shed_over_capacity"] > 3.5
    assert booked["shed_over_capacity"] < 1.3 and booked["held"] > 0
    assert booked["served_share"] > 0.97 and before["served_share"] > 0.97


def test_under_stalls_the_booked_waits_serve_as_much():
    cfg = shed_model.ModelConfig(seconds=20.0, stall_s=0.3, stall_every_s=2.0)
    rows = {p: shed_model.simulate(p, 3.0, cfg) for p in shed_model.POLICIES}
    shares = {p: r["served_share"] for p, r in rows.items()}
    assert all(0.75 < s < 0.92 for s in shares.values()), shares  # 15 % of the time stalled
    assert shares["booked+jitter"] > shares["before"] - 0.03, shares
    assert rows["booked+jitter"]["shed_over_capacity"] < rows["before"]["shed_over_capacity"]


def test_a_computation_overlapping_a_stall_takes_the_stall_longer():
    cfg = shed_model.ModelConfig(stall_s=0.3, stall_every_s=2.0)  # stalls [1.7, 2.0), ...
    assert shed_model._finish_s(1.0, 0.05, cfg) == pytest.approx(1.05)
    assert shed_model._finish_s(1.68, 0.05, cfg) == pytest.approx(2.03)
    assert shed_model._finish_s(1.8, 0.05, cfg) == pytest.approx(2.05)
    with pytest.raises(ValueError, match="policy"):
        shed_model.simulate("fastest", 3.0, cfg)

"""bench/shed_model.py: the server's own Lane on simulated time. Vehicles given booked
waits send about one shed frame per served one, a quarter of what the drain time for
all lets through at 5x; when a request holds its place in the lane before and after its
computation (its body read, its answer sent), waits booked over 60 slots and rounded up
to whole frames leave the lane idle with places free, and the product's waits (spread
over half a frame period, the vehicle back on the nearest frame) serve as vehicles that
ignore the waits do, with fewer sheds; a stall lengthens a computation."""

from __future__ import annotations

import pytest

from bench import shed_model


def test_booked_waits_shed_far_less_and_keep_the_lane_busy():
    cfg = shed_model.ModelConfig(seconds=15.0)
    before = shed_model.simulate("before", 5.0, cfg)
    booked = shed_model.simulate("booked+jitter", 5.0, cfg)
    product = shed_model.simulate("product", 5.0, cfg)
    assert before["vehicles"] == booked["vehicles"] == 23
    # the drain time (90 ms) is shorter than a frame period: nothing held, 4x shed
    assert before["held"] == 0 and before["shed_over_capacity"] > 3.5
    assert booked["shed_over_capacity"] < 1.3 and booked["held"] > 0
    assert product["held"] > 0 and product["shed_over_capacity"] < before["shed_over_capacity"]
    for run in (before, booked, product):
        assert run["served_share"] > 0.97


@pytest.mark.parametrize("overload", [3.0, 5.0])
def test_with_places_held_outside_the_computation_the_product_keeps_the_lane_fed(overload):
    cfg = shed_model.ModelConfig(seconds=20.0, pre_s=0.03, post_s=0.005)
    rows = {p: shed_model.simulate(p, overload, cfg) for p in shed_model.POLICIES}
    served = {p: r["served_share"] for p, r in rows.items()}
    idle = {p: r["idle_with_free_place_share"] for p, r in rows.items()}
    # waits of up to 60 slots, rounded up to whole frames: most of them over a period,
    # the lane idle with a place free twice as long, 3+ points of capacity lost
    assert rows["booked+jitter"]["wait_over_period_share"] > 0.8
    assert served["booked+jitter"] < served["product"] - 0.03, served
    assert idle["booked+jitter"] > 2 * idle["product"], idle
    # the product serves as vehicles sending every frame do, shedding fewer frames
    assert served["product"] > served["every-frame"] - 0.01, served
    shed = {p: r["shed_over_capacity"] for p, r in rows.items()}
    assert shed["product"] < 0.85 * shed["every-frame"], shed


def test_under_stalls_the_booked_waits_serve_as_much():
    cfg = shed_model.ModelConfig(seconds=20.0, stall_s=0.3, stall_every_s=2.0)
    rows = {p: shed_model.simulate(p, 3.0, cfg) for p in shed_model.POLICIES}
    shares = {p: r["served_share"] for p, r in rows.items()}
    assert all(0.75 < s < 0.92 for s in shares.values()), shares  # 15 % of the time stalled
    assert shares["booked+jitter"] > shares["before"] - 0.03, shares
    assert shares["product"] > shares["before"] - 0.03, shares
    assert rows["booked+jitter"]["shed_over_capacity"] < rows["before"]["shed_over_capacity"]
    assert rows["product"]["shed_over_capacity"] < rows["before"]["shed_over_capacity"]


def test_a_computation_overlapping_a_stall_takes_the_stall_longer():
    cfg = shed_model.ModelConfig(stall_s=0.3, stall_every_s=2.0)  # stalls [1.7, 2.0), ...
    assert shed_model._finish_s(1.0, 0.05, cfg) == pytest.approx(1.05)
    assert shed_model._finish_s(1.68, 0.05, cfg) == pytest.approx(2.03)
    assert shed_model._finish_s(1.8, 0.05, cfg) == pytest.approx(2.05)
    with pytest.raises(ValueError, match="policy"):
        shed_model.simulate("fastest", 3.0, cfg)

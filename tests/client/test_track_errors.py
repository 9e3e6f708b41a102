"""Along-/cross-track errors by turning class, best-of-k and time to recover, on
synthetic trajectories with planted errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from monoloc.client.trajectory import (
    TurnClasses,
    best_of_k_errors,
    blurred_best_of_k_errors,
    errors_by_turning,
    excursion_causes,
    frame_errors,
    time_to_recover,
    yaw_rate_of,
)
from monoloc.core.errors import InvalidInputError


def _route(dt_s: float = 0.1):
    """A straight, a gentle left turn (0.15 rad/s), a straight, a sharp right turn
    (-0.5 rad/s), a straight; 8 m/s. Returns times (N,), poses (N, 3), yaw rates (N,)."""
    rates = np.concatenate(
        [np.zeros(40), np.full(60, 0.15), np.zeros(40), np.full(40, -0.5), np.zeros(40)]
    )
    poses = [np.array([5.0, -3.0, 2.5])]
    for rate in rates[:-1]:
        x, y, yaw = poses[-1]
        poses.append(
            np.array([x + 0.8 * math.cos(yaw), y + 0.8 * math.sin(yaw), yaw + rate * dt_s])
        )
    poses = np.array(poses)
    poses[:, 2] = np.arctan2(np.sin(poses[:, 2]), np.cos(poses[:, 2]))
    return np.arange(len(rates)) * dt_s, poses, rates


def _offset(poses: np.ndarray, along_m, cross_m, heading_rad) -> np.ndarray:
    """poses moved by along/cross-track offsets (scalars or (N,)) in their own frame."""
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    out = poses.copy()
    out[:, 0] += along_m * c - cross_m * s
    out[:, 1] += along_m * s + cross_m * c
    out[:, 2] = np.arctan2(np.sin(poses[:, 2] + heading_rad), np.cos(poses[:, 2] + heading_rad))
    return out


def test_frame_errors_recover_planted_along_cross_and_heading():
    _, truth, _ = _route()
    est = _offset(truth, 0.3, -0.2, math.radians(1.0))
    errors = frame_errors(est, truth)
    np.testing.assert_allclose(errors[:, 0], 0.3, atol=1e-12)
    np.testing.assert_allclose(errors[:, 1], -0.2, atol=1e-12)
    np.testing.assert_allclose(errors[:, 2], math.radians(1.0), atol=1e-12)


def test_yaw_rate_and_classes_follow_the_route():
    times, truth, rates = _route()
    measured = yaw_rate_of(truth, times)
    # away from the class changes the differences are exact
    inner = np.abs(np.convolve(np.diff(rates, prepend=rates[0]) != 0, [1, 1, 1], "same")) == 0
    np.testing.assert_allclose(measured[inner][1:-1], rates[inner][1:-1], atol=1e-9)
    names = TurnClasses().classify(measured)
    assert (names[:38] == "straight").all()
    assert (names[45:95] == "turning").all()
    assert (names[145:175] == "sharp").all()


def test_errors_by_turning_separate_an_outward_bias_in_turns():
    times, truth, rates = _route()
    rng = np.random.default_rng(0)
    # 0.1 m to the outside of every turn (right in the left turn, left in the right
    # turn), none on the straights, plus noise.
    outward = -0.1 * np.sign(rates)
    est = _offset(truth, rng.normal(0, 0.01, len(truth)), outward, 0.0)
    est[10] = np.nan  # a frame without estimate is skipped
    seg = errors_by_turning(est, truth, times)
    assert set(seg) == {"straight", "turning", "sharp", "all"}
    assert seg["straight"].cross_mean_m == pytest.approx(0.0, abs=0.01)
    assert seg["turning"].cross_inward_mean_m == pytest.approx(-0.1, abs=0.01)
    assert seg["sharp"].cross_inward_mean_m == pytest.approx(-0.1, abs=0.01)
    # the signed cross-track mean tells left from right: negative in the left turn,
    # positive in the right one
    assert seg["turning"].cross_mean_m < -0.08 and seg["sharp"].cross_mean_m > 0.08
    assert seg["all"].n_frames == len(truth) - 1
    assert abs(seg["all"].along_mean_m) < 0.01


def test_heading_ahead_of_the_turn_is_signed_by_the_turn():
    times, truth, rates = _route()
    est = _offset(truth, 0.0, 0.0, -math.radians(0.5) * np.sign(rates))  # lagging
    seg = errors_by_turning(est, truth, times)
    assert seg["turning"].heading_ahead_mean_deg == pytest.approx(-0.5, abs=0.05)
    assert seg["sharp"].heading_rmse_deg == pytest.approx(0.5, abs=0.05)


def test_best_of_k_picks_the_closest_hypothesis_and_marks_empty_frames():
    truth = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [20.0, 0.0, 0.0]])
    hyps = [
        np.array([[0.3, 0.4, 0.0], [5.0, 5.0, 0.0]]),
        np.zeros((0, 3)),
        np.array([[20.0, 0.1, 0.0]]),
    ]
    best = best_of_k_errors(hyps, truth)
    np.testing.assert_allclose(best, [0.5, np.nan, 0.1])
    with pytest.raises(InvalidInputError):
        best_of_k_errors(hyps[:2], truth)


def _clusters(rng, centre_offset_m, n_frames=400, k=11, spread_m=0.005):
    """Per frame k hypotheses spread spread_m around a point centre_offset_m (in a random
    direction) from the truth, as a frame's hypotheses sit around the map's frame."""
    truth = np.column_stack([np.arange(n_frames) * 1.0, np.zeros(n_frames), np.zeros(n_frames)])
    angle = rng.uniform(0, 2 * np.pi, n_frames)
    centre = truth[:, :2] + centre_offset_m * np.column_stack([np.cos(angle), np.sin(angle)])
    hyps = [np.column_stack([c + rng.normal(0, spread_m, (k, 2)), np.zeros(k)]) for c in centre]
    return hyps, truth


def test_blurring_the_hypotheses_lowers_the_best_of_k_when_the_truth_lies_off_them():
    rng = np.random.default_rng(5)
    hyps, truth = _clusters(rng, centre_offset_m=0.05)
    hyps[3] = np.zeros((0, 3))
    plain = best_of_k_errors(hyps, truth)
    # no blur is the plain oracle, frames without hypotheses stay NaN
    same = blurred_best_of_k_errors(hyps, truth, 0.0, np.random.default_rng(1))
    np.testing.assert_allclose(same, plain)
    blurred = blurred_best_of_k_errors(hyps, truth, 0.02, np.random.default_rng(1))
    assert np.isnan(blurred[3]) and np.isfinite(np.delete(blurred, 3)).all()
    # 5 cm off a 5 mm cluster: the oracle gains from noise that carries nothing
    assert np.nanmedian(blurred) < 0.85 * np.nanmedian(plain)
    # the input is not moved in place
    np.testing.assert_allclose(best_of_k_errors(hyps, truth), plain)
    # the same generator state gives the same draws
    again = blurred_best_of_k_errors(hyps, truth, 0.02, np.random.default_rng(1))
    np.testing.assert_allclose(again, blurred)


def test_blurring_the_hypotheses_raises_the_best_of_k_when_the_truth_is_among_them():
    rng = np.random.default_rng(6)
    hyps, truth = _clusters(rng, centre_offset_m=0.0)
    plain = np.nanmedian(best_of_k_errors(hyps, truth))
    blurred = np.nanmedian(blurred_best_of_k_errors(hyps, truth, 0.02, rng))
    assert blurred > 2.0 * plain
    with pytest.raises(InvalidInputError):
        blurred_best_of_k_errors(hyps, truth, -0.01, rng)
    with pytest.raises(InvalidInputError):
        blurred_best_of_k_errors(hyps, truth, float("nan"), rng)


def test_excursion_causes_sort_the_frames_off_by_their_hypotheses():
    truth = np.column_stack([np.arange(6) * 1.0, np.zeros(6), np.zeros(6)])
    est = truth.copy()
    est[0] = np.nan  # not started
    est[1, 1] += 0.1  # within the tolerance: not off, whatever its hypotheses
    est[2, 1] += 0.4  # off, no hypotheses
    est[3, 1] += 0.4  # off, every hypothesis off too
    est[4, 1] += 0.4  # off, one hypothesis near the truth
    est[5, 1] += 0.26  # just beyond: off, hypotheses exactly on the truth
    hyps = [
        np.array([[0.0, 0.0, 0.0]]),
        np.array([[1.0, 3.0, 0.0]]),
        np.zeros((0, 3)),
        np.array([[3.0, 0.3, 0.0], [3.5, -0.5, 0.0]]),
        np.array([[4.0, 0.6, 0.0], [4.0, 0.2, 0.0]]),
        np.array([[5.0, 0.0, 0.0]]),
    ]
    causes = excursion_causes(est, truth, hyps, tolerance_m=0.25)
    assert (causes.frames, causes.off, causes.no_estimate) == (6, 5, 1)
    assert (causes.no_hypotheses, causes.hypotheses_off, causes.filter_off) == (1, 1, 2)
    assert causes.off == (
        causes.no_estimate + causes.no_hypotheses + causes.hypotheses_off + causes.filter_off
    )
    assert causes.text().startswith("5 of 6 frames beyond 0.25 m: 1 before the start")
    assert causes.to_dict()["filter_off"] == 2
    with pytest.raises(InvalidInputError):
        excursion_causes(est[:5], truth, hyps)
    with pytest.raises(InvalidInputError):
        excursion_causes(est, truth, hyps, tolerance_m=0.0)


def test_time_to_recover_needs_the_error_to_stay_small():
    times = np.arange(30) * 0.1
    err = np.full(30, 20.0)
    err[5] = 0.1  # a lucky frame does not count
    err[12:] = 0.2
    assert time_to_recover(err, times, since=2, hold_frames=5) == pytest.approx(1.0)
    assert time_to_recover(np.full(30, 3.0), times, since=0) == math.inf

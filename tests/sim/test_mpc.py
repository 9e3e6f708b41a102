"""The localization-aware MPC (sim/mpc.py): it tracks a straight and a curved path on the
true pose within the steering angle and rate limits, and the worse the localization, the
closer it keeps to the mapped corridor."""

import math
from dataclasses import replace

import numpy as np
import pytest

from monoloc.client.particle_filter import FilterEstimate
from monoloc.core.errors import InvalidInputError
from monoloc.sim.closed_loop import LoopConfig, make_controller, quality_of
from monoloc.sim.control import (
    BicycleState,
    Command,
    TrackingController,
    step_bicycle,
)
from monoloc.sim.indoor.plan import SCALE_CAR_BICYCLE
from monoloc.sim.mpc import (
    LocalizationQuality,
    MpcConfig,
    MpcController,
    quality_factor,
    view_weight,
)
from monoloc.sim.path import resample

CAR = SCALE_CAR_BICYCLE  # the indoor 1:10 car
DT_S = 0.005
LOST = LocalizationQuality(position_std_m=0.05, yaw_std_rad=math.radians(5.0), known_share=0.0)
SURE = LocalizationQuality(position_std_m=0.0, yaw_std_rad=0.0, known_share=0.6)


def _straight_then_curve(radius_m: float = 2.0):
    """A 20 m straight, then a left half circle."""
    s = np.linspace(0.0, 20.0, 201)
    straight = np.stack([s, np.zeros_like(s)], axis=1)
    theta = np.linspace(0.0, np.pi, 300)
    arc = np.stack([20 + radius_m * np.sin(theta), radius_m * (1 - np.cos(theta))], axis=1)
    return resample(np.vstack([straight, arc[1:]]), 0.02)


def _mpc(path, quality=None, **overrides):
    config = replace(MpcConfig.for_vehicle(CAR, 1.0, 0.1), **overrides)
    return MpcController(path, config, CAR, quality=quality)


def _follow(controller, state, seconds, disturbance=None):
    """Drive on the true pose; (lateral errors, steering commands, final state).
    ``disturbance(t)``: an actuator offset the controller does not know, added to its
    steering command."""
    lateral, steer = [], []
    for k in range(round(seconds / DT_S)):
        t = k * DT_S
        command, err = controller.command(
            t, state.x_m, state.y_m, state.yaw_rad, state.speed_mps, DT_S
        )
        lateral.append(err.lateral_m)
        steer.append(command.steer_rad)
        if disturbance is not None:
            command = Command(command.steer_rad + disturbance(t), command.accel_mps2)
        state = step_bicycle(state, command, CAR, DT_S)
        if controller.at_end:
            break
    return np.array(lateral), np.array(steer), state


def _assert_within_limits(steer):
    assert np.all(np.abs(steer) <= CAR.max_steer_rad + 1e-9)
    assert np.max(np.abs(np.diff(steer))) / DT_S <= CAR.max_steer_rate_radps * (1 + 1e-6)


def test_mpc_converges_on_a_straight_from_an_offset_within_the_limits():
    path = _straight_then_curve()
    controller = _mpc(path)
    lateral, steer, state = _follow(controller, BicycleState(0.0, 0.3, 0.1, 0.6), 14.0)
    assert lateral[0] == pytest.approx(0.3, abs=1e-6)
    # 0.3 m off and heading away: the steering saturates (angle or rate) on the way back.
    assert np.max(np.abs(steer)) > 0.9 * CAR.max_steer_rad
    _assert_within_limits(steer)
    assert np.all(np.abs(lateral[round(4 / DT_S) :]) < 0.003)  # on the line after 4 s
    assert abs(lateral[-1]) < 0.002
    assert state.speed_mps == pytest.approx(1.0, abs=0.01)  # the reference speed
    # Every re-plan solved (its time is bench/mpc.py's: the wall-time bound that stood
    # here failed a run at load ~11 and passed the next one).
    assert controller.solve_times_s and controller.failed_solves == 0


def test_mpc_holds_a_tight_curve_better_than_the_pid():
    path = _straight_then_curve(radius_m=1.0)  # steady steering 0.26 rad of 0.45
    start = BicycleState(16.0, 0.0, 0.0, 1.0)  # the curve starts 4 s on
    lateral, steer, _ = _follow(_mpc(path), start, 9.0)
    in_curve = lateral[round(5 / DT_S) :]
    assert len(in_curve) > round(2 / DT_S) and np.max(np.abs(in_curve)) < 0.01
    _assert_within_limits(steer)
    pid_lateral, _, _ = _follow(make_controller("pid", _World(), path), start, 9.0)
    assert np.max(np.abs(in_curve)) < np.max(np.abs(pid_lateral[round(5 / DT_S) :]))


def test_low_quality_keeps_the_car_closer_to_the_mapped_corridor():
    """An actuator offset the model does not know pushes the car off the line: with the
    localization lost, the view term holds it nearer the corridor's centre than with a
    sure localization; with the term's weight 0 quality makes no difference."""
    path = _straight_then_curve()

    def push(t):
        return 0.02 + 0.06 * math.sin(2 * math.pi * t / 2.5)

    def rms(quality, **overrides):
        start = BicycleState(0.0, 0.0, 0.0, 1.0)
        lateral, steer, _ = _follow(_mpc(path, quality, **overrides), start, 24.0, push)
        _assert_within_limits(steer)
        return float(np.sqrt(np.mean(lateral[round(2 / DT_S) :] ** 2)))

    sure, lost = rms(SURE), rms(LOST)
    assert lost < 0.85 * sure
    assert rms(SURE, view_weight=0.0) == pytest.approx(rms(LOST, view_weight=0.0), rel=1e-9)


def test_quality_factor_follows_the_stated_formula():
    config = MpcConfig()
    assert quality_factor(None, config) == 1.0
    assert quality_factor(SURE, config) == 1.0
    assert quality_factor(LOST, config) == 0.0
    half = LocalizationQuality(config.position_std_ref_m, 0.0, 2 * config.known_share_ref)
    assert quality_factor(half, config) == pytest.approx(0.5)
    some = LocalizationQuality(0.0, config.yaw_std_ref_rad, 0.5 * config.known_share_ref)
    assert quality_factor(some, config) == pytest.approx(0.25)
    assert view_weight(some, config) == pytest.approx(0.75 * config.view_weight)
    with pytest.raises(InvalidInputError):
        LocalizationQuality(math.nan, 0.0, 0.5)
    with pytest.raises(InvalidInputError):
        LocalizationQuality(0.01, 0.0, -0.1)


def test_quality_of_a_filter_estimate():
    cov = np.diag([0.03**2, 0.01**2, math.radians(2.0) ** 2])
    estimate = FilterEstimate(np.zeros(3), cov, 500.0, 3, False)
    q = quality_of(estimate, known_share=0.4)
    assert q.position_std_m == pytest.approx(0.03)
    assert q.yaw_std_rad == pytest.approx(math.radians(2.0))
    assert q.known_share == pytest.approx(0.4)


@pytest.mark.parametrize(
    "overrides",
    [
        {"horizon_s": 0.0},
        {"step_s": -0.1},
        {"lateral_scale_m": math.nan},
        {"view_weight": -1.0},
        {"horizon_s": 30.0},
        {"max_iterations": 0},
    ],
)
def test_bad_mpc_settings_are_refused(overrides):
    with pytest.raises(InvalidInputError):
        MpcConfig(**overrides)


class _World:
    """What make_controller reads of a closed-loop world (the indoor car's values)."""

    bicycle = CAR
    reference_speed_mps = 1.0
    lane_half_width_m = 0.25
    natural_freq_radps = 2.0
    disturbance_rad = 0.25
    disturbance_period_s = 2.5

    def controller_config(self, disturbance, phase_rad=0.0):
        from monoloc.sim.closed_loop_world import controller_config_for

        return controller_config_for(self, disturbance, phase_rad)


def test_loop_config_and_factory_choose_the_controller():
    path = _straight_then_curve()
    assert isinstance(make_controller("pid", _World(), path), TrackingController)
    mpc = make_controller("mpc", _World(), path)
    assert isinstance(mpc, MpcController)
    assert mpc.config.corridor_half_width_m == pytest.approx(0.1)
    assert LoopConfig().controller == "pid" and LoopConfig(controller="mpc").controller == "mpc"
    with pytest.raises(InvalidInputError, match="controller must be one of"):
        LoopConfig(controller="lqr")
    with pytest.raises(InvalidInputError, match="disturbance"):
        LoopConfig(controller="mpc", disturbance=True)
    with pytest.raises(InvalidInputError):
        make_controller("mpc", _World(), path, disturbance=True)

"""The closed-loop vehicle: kinematic bicycle (limits, lag, arcs) and the PID tracking
controller (converges from an offset, holds a curve, the disturbance oscillates)."""

import math

import numpy as np
import pytest

from monoloc.core.errors import InvalidInputError
from monoloc.sim.control import (
    BicycleConfig,
    BicycleState,
    Command,
    ControllerConfig,
    Pid,
    PidGains,
    TrackingController,
    step_bicycle,
    tracking_error,
)
from monoloc.sim.indoor.plan import SCALE_CAR_BICYCLE
from monoloc.sim.path import resample

CAR = SCALE_CAR_BICYCLE  # the indoor 1:10 car


def _drive(state, command, config, seconds, dt=0.005):
    for _ in range(round(seconds / dt)):
        state = step_bicycle(state, command, config, dt)
    return state


def test_constant_steering_drives_the_bicycle_circle():
    steer = 0.3
    config = BicycleConfig(wheelbase_m=0.26, steer_lag_s=0.0, max_steer_rate_radps=100.0)
    start = BicycleState(0.0, 0.0, 0.0, 1.0, steer_rad=steer)
    radius = 0.26 / math.tan(steer)
    end = _drive(start, Command(steer, 0.0), config, seconds=math.pi * radius)  # half circle
    assert end.yaw_rad == pytest.approx(math.pi, abs=2e-3)
    assert end.x_m == pytest.approx(0.0, abs=2e-3)
    assert end.y_m == pytest.approx(2 * radius, abs=2e-3)


def test_steering_is_clipped_rate_limited_and_lagged():
    start = BicycleState(0.0, 0.0, 0.0, 1.0)
    after_10ms = _drive(start, Command(2.0, 0.0), CAR, seconds=0.01)
    assert after_10ms.steer_rad == pytest.approx(4.0 * 0.01)  # rate limit
    lag_only = BicycleConfig(wheelbase_m=0.26, max_steer_rate_radps=100.0, steer_lag_s=0.05)
    one_tau = _drive(start, Command(0.2, 0.0), lag_only, seconds=0.05)
    assert one_tau.steer_rad == pytest.approx(0.2 * (1 - math.exp(-1)), rel=1e-3)
    settled = _drive(start, Command(2.0, 0.0), CAR, seconds=1.0)
    assert settled.steer_rad == pytest.approx(CAR.max_steer_rad)  # clipped


def test_speed_respects_acceleration_limits_and_never_reverses():
    start = BicycleState(0.0, 0.0, 0.0, 1.0)
    dt_s, seconds = 0.005, 1.0
    faster = _drive(start, Command(0.0, 50.0), CAR, seconds=seconds, dt=dt_s)
    # 50 m/s^2 asked, clipped to 1 m/s^2, then lagged (tau 0.1 s): step k accelerates at
    # 1 - r^k with r = exp(-dt / tau), so N steps gain dt (N - r (1 - r^N) / (1 - r)).
    n, r = round(seconds / dt_s), math.exp(-dt_s / CAR.accel_lag_s)
    gained = dt_s * (n - r * (1 - r**n) / (1 - r))
    assert faster.speed_mps == pytest.approx(1.0 + gained, rel=1e-9)
    # ... which is the continuous lag's 1 - tau (1 - e^(-T / tau)) = 0.9 m/s to 3 mm/s
    assert gained == pytest.approx(1.0 - 0.1 * (1 - math.exp(-10.0)), abs=3e-3)
    stopped = _drive(start, Command(0.0, -50.0), CAR, seconds=3.0)
    assert stopped.speed_mps == 0.0
    fast = _drive(BicycleState(0, 0, 0, 2.9), Command(0.0, 50.0), CAR, seconds=2.0)
    assert fast.speed_mps == CAR.max_speed_mps


def test_invalid_configs_are_refused():
    with pytest.raises(InvalidInputError):
        BicycleConfig(wheelbase_m=0.0)
    with pytest.raises(InvalidInputError):
        BicycleConfig(steer_lag_s=-0.1)


def test_pid_terms_and_integral_limit():
    pid = Pid(PidGains(kp=2.0, ki=1.0, kd=0.5, integral_limit=0.3))
    assert pid(1.0, 0.1) == pytest.approx(-(2.0 + 0.1))  # no derivative on the first call
    out = pid(1.5, 0.1)
    assert out == pytest.approx(-(3.0 + 0.25 + 0.5 * 5.0))
    for _ in range(100):
        pid(1.0, 0.1)
    assert pid.integral == pytest.approx(0.3)


def _test_path():
    """A 20 m straight, then a left half circle of 2 m radius."""
    s = np.linspace(0.0, 20.0, 201)
    straight = np.stack([s, np.zeros_like(s)], axis=1)
    theta = np.linspace(0.0, np.pi, 300)
    arc = np.stack([20 + 2 * np.sin(theta), 2 - 2 * np.cos(theta)], axis=1)
    return resample(np.vstack([straight, arc[1:]]), 0.02)


def _follow(controller, state, seconds, dt=0.005):
    lateral = []
    for k in range(round(seconds / dt)):
        command, err = controller.command(
            k * dt, state.x_m, state.y_m, state.yaw_rad, state.speed_mps, dt
        )
        state = step_bicycle(state, command, CAR, dt)
        lateral.append(err.lateral_m)
        if controller.at_end:
            break
    return state, np.array(lateral)


def test_controller_converges_to_the_path_from_an_offset_and_holds_the_curve():
    path = _test_path()
    controller = TrackingController(path, ControllerConfig.for_vehicle(CAR, 1.0, 2.0), CAR)
    state, lateral = _follow(controller, BicycleState(0.0, 0.3, 0.1, 0.6), seconds=40.0)
    assert lateral[0] == pytest.approx(0.3, abs=1e-6)
    assert np.all(np.abs(lateral[round(8 / 0.005) :]) < 0.03)  # after 8 s, in the curve too
    assert abs(lateral[-1]) < 0.005
    assert state.speed_mps == pytest.approx(1.0, abs=0.02)  # the reference speed


def test_disturbance_makes_an_oscillating_off_center_lap():
    path = _test_path()
    config = ControllerConfig.for_vehicle(
        CAR, 1.0, 2.0, disturbance_rad=0.25, disturbance_period_s=2.5
    )
    _, lateral = _follow(TrackingController(path, config, CAR), BicycleState(0, 0, 0, 1.0), 20.0)
    steady = lateral[round(4 / 0.005) :]
    assert 0.05 < np.max(np.abs(steady)) < 0.25  # off the line, inside a 0.7 m track
    crossings = np.sum(np.diff(np.sign(steady)) != 0)
    assert crossings >= 2 * (len(steady) * 0.005 / 2.5) - 2  # two per disturbance period


def test_tracking_error_signs():
    path = _test_path()
    left = tracking_error(path, 5.0, 0.2, 0.1)
    assert left.lateral_m == pytest.approx(0.2, abs=1e-6)
    assert left.heading_rad == pytest.approx(0.1, abs=1e-3)
    right = tracking_error(path, 5.0, -0.2, -0.1)
    assert right.lateral_m == pytest.approx(-0.2, abs=1e-6)


def test_episodes_group_consecutive_frames():
    from monoloc.sim.closed_loop_metrics import episodes

    mask = np.array([0, 1, 1, 0, 0, 1, 0, 1], dtype=bool)
    assert episodes(mask) == [(1, 3), (5, 6), (7, 8)]
    assert episodes(np.zeros(4, dtype=bool)) == []


def test_passes_over_a_stretch_pool_into_one_result_and_each_pass_settles():
    """A route that is no loop is driven again from its start: the passes' frames follow
    each other in time, and each pass's filter start is no spike while a later excursion
    is one."""
    from monoloc.sim.closed_loop import LoopConfig, concat_passes, run_loop
    from monoloc.sim.closed_loop_metrics import SETTLE_S, loop_metrics
    from monoloc.sim.closed_loop_world import IndoorLoopWorld

    world = IndoorLoopWorld("small", seed=0)
    drives = [run_loop(world, LoopConfig(mode="open", max_frames=40, seed=s)) for s in (1, 2)]
    for drive in drives:  # an estimate 1 cm off, 2 m off on the first frame (the start)
        drive.estimates_world = drive.frames["truth_cam"].copy()
        drive.estimates_world[:, 0] += 0.01
        drive.estimates_world[0, 0] += 2.0
    first_settled = np.flatnonzero(drives[1].frames["t_s"] - drives[1].frames["t_s"][0] >= SETTLE_S)
    drives[1].estimates_world[first_settled[0] + 2, 1] += 1.0  # one excursion, settled
    both = concat_passes(drives)
    n = [d.n_frames for d in drives]
    assert both.n_frames == sum(n) and len(both.estimates_world) == sum(n)
    assert np.all(np.diff(both.frames["t_s"]) > 0) and np.all(np.diff(both.trace["t_s"]) > 0)
    assert both.frames["pass_index"].tolist() == [0] * n[0] + [1] * n[1]
    np.testing.assert_array_equal(both.frames["lateral_m"][n[0] :], drives[1].frames["lateral_m"])
    m = loop_metrics(both, spike_threshold_m=0.5)
    assert m["spikes"] == 1 and m["frames"] == sum(n)
    assert concat_passes(drives[:1]).frames["pass_index"].tolist() == [0] * n[0]
    with pytest.raises(InvalidInputError):
        concat_passes([])

"""A vehicle that can be steered: a kinematic bicycle with actuator limits and lag, and a
PID trajectory-tracking controller (speed, lateral error, heading error to a reference
path), with an optional sinusoidal steering disturbance (the paper's oscillating,
off-center mapping laps).

Frames: the z-up world's xy plane; the vehicle's reference point is the rear axle (as in
``monoloc.sim.vehicle``); yaw counter-clockwise from +x. Lateral error is positive when
the vehicle is left of the path, heading error is the vehicle's yaw minus the path's
heading, wrapped to (-pi, pi].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.sim.path import Path


@dataclass(frozen=True)
class BicycleConfig:
    """Kinematic bicycle: wheelbase, steering and speed limits, first-order actuator lags
    (time constants; 0 = instantaneous). Units m, rad, s."""

    wheelbase_m: float = 2.7
    max_steer_rad: float = 0.6
    max_steer_rate_radps: float = 0.8
    max_speed_mps: float = 20.0
    max_accel_mps2: float = 1.5
    max_decel_mps2: float = 3.0
    steer_lag_s: float = 0.1
    accel_lag_s: float = 0.2

    def __post_init__(self) -> None:
        if self.wheelbase_m <= 0 or self.max_steer_rad <= 0 or self.max_speed_mps <= 0:
            raise InvalidInputError("wheelbase, steering and speed limits must be positive")
        if self.steer_lag_s < 0 or self.accel_lag_s < 0:
            raise InvalidInputError("actuator lags must be >= 0")


@dataclass(frozen=True)
class BicycleState:
    """Rear-axle pose (x_m, y_m, yaw_rad unwrapped), speed, the actual steering angle and
    longitudinal acceleration (the actuators' outputs)."""

    x_m: float
    y_m: float
    yaw_rad: float
    speed_mps: float
    steer_rad: float = 0.0
    accel_mps2: float = 0.0

    def yaw_rate_radps(self, config: BicycleConfig) -> float:
        return self.speed_mps * math.tan(self.steer_rad) / config.wheelbase_m


@dataclass(frozen=True)
class Command:
    """What the controller asks of the actuators."""

    steer_rad: float
    accel_mps2: float


def _lag(actual: float, wanted: float, lag_s: float, dt_s: float) -> float:
    """One exact step of a first-order lag towards ``wanted``."""
    if lag_s <= 0.0:
        return wanted
    return actual + (wanted - actual) * (1.0 - math.exp(-dt_s / lag_s))


def step_bicycle(
    state: BicycleState, command: Command, config: BicycleConfig, dt_s: float
) -> BicycleState:
    """The state ``dt_s`` later. The commands are clipped to the limits, go through the
    actuators' lags (steering also rate-limited), then the pose moves along the arc of
    constant speed and yaw rate over the step."""
    wanted_steer = float(np.clip(command.steer_rad, -config.max_steer_rad, config.max_steer_rad))
    steer = _lag(state.steer_rad, wanted_steer, config.steer_lag_s, dt_s)
    max_step = config.max_steer_rate_radps * dt_s
    steer = state.steer_rad + float(np.clip(steer - state.steer_rad, -max_step, max_step))
    wanted_accel = float(np.clip(command.accel_mps2, -config.max_decel_mps2, config.max_accel_mps2))
    accel = _lag(state.accel_mps2, wanted_accel, config.accel_lag_s, dt_s)
    v0 = state.speed_mps
    v1 = float(np.clip(v0 + accel * dt_s, 0.0, config.max_speed_mps))
    v = 0.5 * (v0 + v1)
    yaw_rate = v * math.tan(steer) / config.wheelbase_m
    dyaw = yaw_rate * dt_s
    yaw_mid = state.yaw_rad + 0.5 * dyaw
    # Chord of the arc: length v dt * sinc(dyaw / 2), along the mid-step heading.
    chord = v * dt_s * (1.0 if abs(dyaw) < 1e-9 else math.sin(0.5 * dyaw) / (0.5 * dyaw))
    return BicycleState(
        x_m=state.x_m + chord * math.cos(yaw_mid),
        y_m=state.y_m + chord * math.sin(yaw_mid),
        yaw_rad=state.yaw_rad + dyaw,
        speed_mps=v1,
        steer_rad=steer,
        accel_mps2=(v1 - v0) / dt_s,
    )


@dataclass(frozen=True)
class PidGains:
    """kp, ki, kd of one loop; ``integral_limit`` bounds the integral term's state (the
    error's integral, in error units x s) against wind-up."""

    kp: float
    ki: float = 0.0
    kd: float = 0.0
    integral_limit: float = math.inf


class Pid:
    """A PID on an error signal: output = -(kp e + ki integral(e) + kd de/dt). The
    derivative is of the error (first call: 0)."""

    def __init__(self, gains: PidGains) -> None:
        self.gains = gains
        self.integral = 0.0
        self._last: float | None = None

    def __call__(self, error: float, dt_s: float) -> float:
        g = self.gains
        self.integral = float(
            np.clip(self.integral + error * dt_s, -g.integral_limit, g.integral_limit)
        )
        derivative = 0.0 if self._last is None or dt_s <= 0 else (error - self._last) / dt_s
        self._last = error
        return -(g.kp * error + g.ki * self.integral + g.kd * derivative)


def lateral_gains(
    wheelbase_m: float, speed_mps: float, natural_freq_radps: float, damping: float = 0.8
) -> tuple[PidGains, PidGains]:
    """(lateral, heading) proportional gains that place the poles of the linearised
    path-following loop (e_lat' = v e_head, e_head' = v / L * steer) at
    s^2 + 2 zeta w s + w^2; a small integral on the lateral error removes the offset
    that actuator lag and curvature leave."""
    k_lat = natural_freq_radps**2 * wheelbase_m / speed_mps**2
    k_head = 2.0 * damping * natural_freq_radps * wheelbase_m / speed_mps
    lateral = PidGains(kp=k_lat, ki=0.1 * k_lat * natural_freq_radps, integral_limit=0.5)
    return lateral, PidGains(kp=k_head)


@dataclass(frozen=True)
class ControllerConfig:
    """The tracking controller: constant reference speed, the speed / lateral / heading
    PIDs, and the steering disturbance (amplitude 0 = none) added to the steering
    command: amplitude * sin(2 pi t / period + phase)."""

    reference_speed_mps: float
    speed: PidGains
    lateral: PidGains
    heading: PidGains
    disturbance_rad: float = 0.0
    disturbance_period_s: float = 4.0
    disturbance_phase_rad: float = 0.0

    @classmethod
    def for_vehicle(
        cls,
        bicycle: BicycleConfig,
        reference_speed_mps: float,
        natural_freq_radps: float,
        disturbance_rad: float = 0.0,
        disturbance_period_s: float = 4.0,
    ) -> ControllerConfig:
        lateral, heading = lateral_gains(
            bicycle.wheelbase_m, reference_speed_mps, natural_freq_radps
        )
        return cls(
            reference_speed_mps=reference_speed_mps,
            speed=PidGains(kp=1.5, ki=0.3, integral_limit=2.0),
            lateral=lateral,
            heading=heading,
            disturbance_rad=disturbance_rad,
            disturbance_period_s=disturbance_period_s,
        )


@dataclass(frozen=True)
class TrackingError:
    """Where a pose is relative to the path: index of the nearest path point, lateral
    error (m, left positive), heading error (rad, wrapped), the path's curvature there."""

    index: int
    lateral_m: float
    heading_rad: float
    curvature_per_m: float


def wrap_angle(a: float) -> float:
    return math.atan2(math.sin(a), math.cos(a))


def tracking_error(
    path: Path, x_m: float, y_m: float, yaw_rad: float, hint: int = 0, window: int = 400
) -> TrackingError:
    """The pose's error to ``path``, searching the nearest point from ``hint`` forward
    over ``window`` points (a path that loops on itself is found lap by lap), then
    projecting onto the segment there."""
    n = len(path.s_m)
    lo = max(0, min(hint, n - 1) - 20)
    hi = min(n, lo + window)
    d2 = np.sum((path.xy[lo:hi] - (x_m, y_m)) ** 2, axis=1)
    i = lo + int(np.argmin(d2))
    heading = float(path.heading_rad[i])
    tangent = (math.cos(heading), math.sin(heading))
    dx, dy = x_m - path.xy[i, 0], y_m - path.xy[i, 1]
    lateral = -tangent[1] * dx + tangent[0] * dy
    return TrackingError(
        index=i,
        lateral_m=float(lateral),
        heading_rad=wrap_angle(yaw_rad - heading),
        curvature_per_m=float(path.curvature[i]),
    )


@dataclass
class TrackingController:
    """Steers a bicycle along ``path`` at the reference speed, from a believed pose
    (the truth in open loop, the localization estimate in closed loop).
    Steering = curvature feed-forward + lateral PID + heading PID + disturbance."""

    path: Path
    config: ControllerConfig
    bicycle: BicycleConfig
    _speed_pid: Pid = field(init=False)
    _lateral_pid: Pid = field(init=False)
    _heading_pid: Pid = field(init=False)
    _hint: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        self._speed_pid = Pid(self.config.speed)
        self._lateral_pid = Pid(self.config.lateral)
        self._heading_pid = Pid(self.config.heading)

    def error(self, x_m: float, y_m: float, yaw_rad: float) -> TrackingError:
        """Tracking error of a pose, continuing the search from the last one."""
        err = tracking_error(self.path, x_m, y_m, yaw_rad, self._hint)
        self._hint = err.index
        return err

    def command(
        self, t_s: float, x_m: float, y_m: float, yaw_rad: float, speed_mps: float, dt_s: float
    ) -> tuple[Command, TrackingError]:
        """The command at time ``t_s`` for a believed rear-axle pose and measured speed."""
        c = self.config
        err = self.error(x_m, y_m, yaw_rad)
        feed_forward = math.atan(self.bicycle.wheelbase_m * err.curvature_per_m)
        steer = (
            feed_forward
            + self._lateral_pid(err.lateral_m, dt_s)
            + self._heading_pid(err.heading_rad, dt_s)
        )
        if c.disturbance_rad:
            steer += c.disturbance_rad * math.sin(
                2.0 * math.pi * t_s / c.disturbance_period_s + c.disturbance_phase_rad
            )
        accel = self._speed_pid(speed_mps - c.reference_speed_mps, dt_s)
        return Command(steer_rad=steer, accel_mps2=accel), err

    @property
    def at_end(self) -> bool:
        return self._hint >= len(self.path.s_m) - 2

"""A localization-aware model predictive controller (the paper's future work).

Every ``MpcConfig.step_s`` (10 Hz by default) it solves, with CasADi, a nonlinear
program over a horizon of ``horizon_s``: the kinematic bicycle of ``sim.control``
(rear axle, wheelbase L) in the path's frame, multiple shooting, RK4 over each step,

    states  x = (e_lat m, e_head rad, steer rad, speed m/s)
    inputs  u = (steer rate rad/s, acceleration m/s^2)
    s'      = v cos(e_head) / (1 - kappa e_lat)
    e_lat'  = v sin(e_head)
    e_head' = v tan(steer) / L - kappa s'

with kappa the path's curvature where the previous plan (or the reference speed) puts
the vehicle at that step; |steer|, |steer rate|, the acceleration and the speed are
bounded by the ``BicycleConfig``. Between solves the command follows the plan: the
steering angle ramps along the planned rate, so the command itself never exceeds the
rate limit.

Stage cost (each term a squared ratio to its scale in ``MpcConfig``)

    (e_lat / lateral_scale)^2 + (e_head / heading_scale)^2 + ((v - v_ref) / speed_scale)^2
    + ((steer - atan(L kappa)) / steer_scale)^2 + (rate / steer_rate_scale)^2
    + (accel / accel_scale)^2
    + w_view(q) [ (e_lat / corridor_half_width)^2 + (e_head / corridor_heading)^2 ]

(the terminal state weighs ``terminal_weight`` stages). The last term keeps the camera
in the mapped view: the mapping laps drove the path's centre line, so the corridor the
map holds is centred on it, and leaving it sideways or looking away from it shows the
camera what the map never held. Its weight grows as the localization's quality q drops:

    w_view(q) = view_weight * (1 - q)
    q = clip(known_share / known_share_ref, 0, 1)
        / (1 + (position_std / position_std_ref)^2 + (yaw_std / yaw_std_ref)^2)

from the particle filter's covariance (position std: the largest eigenvalue's root,
``FilterEstimate.position_std_m``; yaw std: sqrt of its yaw variance) and the share of
the query's features the map explains (``closed_loop.answer_counts``: inliers over
features). q = 1 (trusted, well inside the map) until a quality is handed over with
:meth:`MpcController.set_quality`.

Frames and signs as ``sim.control``: lateral error positive left of the path, heading
error the vehicle's yaw minus the path's heading.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.sim.control import BicycleConfig, Command, TrackingError, tracking_error
from monoloc.sim.path import Path


@dataclass(frozen=True)
class LocalizationQuality:
    """What the controller is told of the localization: the filter's position std (m,
    root of the largest eigenvalue of its position covariance), its yaw std (rad), and
    the share of the query's features the map explains (0..1; 0 without an answer)."""

    position_std_m: float
    yaw_std_rad: float
    known_share: float

    def __post_init__(self) -> None:
        values = (self.position_std_m, self.yaw_std_rad, self.known_share)
        if not all(math.isfinite(v) and v >= 0 for v in values):
            raise InvalidInputError(f"localization quality must be finite and >= 0: {values}")


@dataclass(frozen=True)
class MpcConfig:
    """The MPC's horizon, cost scales and quality rule (see the module docstring).

    Defaults are the 1:10 indoor car at 1 m/s; :meth:`for_vehicle` scales the lengths
    with the wheelbase and the speed. ``horizon_s`` 1.5 s = 15 steps of 0.1 s (the
    re-solve period too: 10 Hz). Scales: lateral 4 cm and heading 0.1 rad are what one
    unit of cost tolerates; the steering regularisation is about the curvature's
    feed-forward angle. ``view_weight`` 20 over a 10 cm, 0.3 rad corridor: at q = 0 the
    lateral weight is 4.2x and the heading weight 3.2x the tracking terms' alone.
    ``known_share_ref`` 0.3: a frame whose best answer explains 30 % of its features
    counts as fully known (centre-line drives of the indoor sim explain 35-55 %);
    ``position_std_ref_m`` 1 cm (``for_vehicle``: a fifth of the corridor's half width)
    and ``yaw_std_ref_rad`` 1 deg: a filter that uncertain halves q.
    ``max_iterations``: SQP iterations per solve (each a QP by qrqp)."""

    reference_speed_mps: float = 1.0
    horizon_s: float = 1.5
    step_s: float = 0.1
    lateral_scale_m: float = 0.04
    heading_scale_rad: float = 0.1
    speed_scale_mps: float = 0.1
    steer_scale_rad: float = 0.3
    steer_rate_scale_radps: float = 2.0
    accel_scale_mps2: float = 1.0
    terminal_weight: float = 5.0
    corridor_half_width_m: float = 0.1
    corridor_heading_rad: float = 0.3
    view_weight: float = 20.0
    known_share_ref: float = 0.3
    position_std_ref_m: float = 0.01
    yaw_std_ref_rad: float = math.radians(1.0)
    max_iterations: int = 8

    def __post_init__(self) -> None:
        positive = {
            name: getattr(self, name)
            for name in (
                "reference_speed_mps",
                "horizon_s",
                "step_s",
                "lateral_scale_m",
                "heading_scale_rad",
                "speed_scale_mps",
                "steer_scale_rad",
                "steer_rate_scale_radps",
                "accel_scale_mps2",
                "corridor_half_width_m",
                "corridor_heading_rad",
                "known_share_ref",
                "position_std_ref_m",
                "yaw_std_ref_rad",
            )
        }
        bad = [name for name, v in positive.items() if not (math.isfinite(v) and v > 0)]
        if bad:
            raise InvalidInputError(f"MPC settings must be positive and finite: {bad}")
        if self.view_weight < 0 or self.terminal_weight < 0:
            raise InvalidInputError("view_weight and terminal_weight must be >= 0")
        if not 1 <= self.steps <= 100:
            raise InvalidInputError(
                f"the horizon must hold 1..100 steps, got {self.horizon_s} s / {self.step_s} s"
            )
        if self.max_iterations < 1:
            raise InvalidInputError("max_iterations must be at least 1")

    @property
    def steps(self) -> int:
        return round(self.horizon_s / self.step_s)

    @classmethod
    def for_vehicle(
        cls, bicycle: BicycleConfig, reference_speed_mps: float, corridor_half_width_m: float
    ) -> MpcConfig:
        """The defaults scaled to a vehicle: lateral scale 15 % of the wheelbase, speed
        scale a tenth of the reference speed, the corridor as given (how far off the
        mapping laps' line the map still explains a view), and the position std that
        halves q a fifth of the corridor's half width (2 cm for the indoor car's 10 cm)."""
        return cls(
            reference_speed_mps=reference_speed_mps,
            lateral_scale_m=0.154 * bicycle.wheelbase_m,
            speed_scale_mps=0.1 * reference_speed_mps,
            corridor_half_width_m=corridor_half_width_m,
            position_std_ref_m=0.2 * corridor_half_width_m,
        )


def quality_factor(quality: LocalizationQuality | None, config: MpcConfig) -> float:
    """q in [0, 1] of the module docstring (1 without a quality)."""
    if quality is None:
        return 1.0
    share = min(1.0, quality.known_share / config.known_share_ref)
    spread = (quality.position_std_m / config.position_std_ref_m) ** 2 + (
        quality.yaw_std_rad / config.yaw_std_ref_rad
    ) ** 2
    return share / (1.0 + spread)


def view_weight(quality: LocalizationQuality | None, config: MpcConfig) -> float:
    """w_view(q) = view_weight * (1 - q)."""
    return config.view_weight * (1.0 - quality_factor(quality, config))


class _Problem:
    """The horizon's NLP, built once: decision vector [X (4, N+1), U (2, N)] column by
    column; parameters [x0 (4), kappa (N), v_ref, w_view]."""

    def __init__(self, config: MpcConfig, bicycle: BicycleConfig) -> None:
        import casadi as ca

        c, n = config, config.steps
        L, h = bicycle.wheelbase_m, c.step_s
        x = ca.SX.sym("x", 4)
        u = ca.SX.sym("u", 2)
        kappa = ca.SX.sym("kappa")

        def f(x, u, kappa):
            e_lat, e_head, steer, v = x[0], x[1], x[2], x[3]
            s_dot = v * ca.cos(e_head) / (1 - kappa * e_lat)
            return ca.vertcat(v * ca.sin(e_head), v * ca.tan(steer) / L - kappa * s_dot, u[0], u[1])

        k1 = f(x, u, kappa)
        k2 = f(x + 0.5 * h * k1, u, kappa)
        k3 = f(x + 0.5 * h * k2, u, kappa)
        k4 = f(x + h * k3, u, kappa)
        step = ca.Function("step", [x, u, kappa], [x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)])

        X = ca.SX.sym("X", 4, n + 1)
        U = ca.SX.sym("U", 2, n)
        P = ca.SX.sym("P", 4 + n + 2)
        x0, kappas, v_ref, w_view = P[:4], P[4 : 4 + n], P[4 + n], P[5 + n]

        def state_cost(xk, kap):
            tracking = (
                (xk[0] / c.lateral_scale_m) ** 2
                + (xk[1] / c.heading_scale_rad) ** 2
                + ((xk[3] - v_ref) / c.speed_scale_mps) ** 2
                + ((xk[2] - ca.atan(L * kap)) / c.steer_scale_rad) ** 2
            )
            view = (xk[0] / c.corridor_half_width_m) ** 2 + (xk[1] / c.corridor_heading_rad) ** 2
            return tracking + w_view * view

        cost = 0
        constraints = [X[:, 0] - x0]
        for k in range(n):
            cost += state_cost(X[:, k], kappas[k]) if k > 0 else 0
            cost += (U[0, k] / c.steer_rate_scale_radps) ** 2 + (U[1, k] / c.accel_scale_mps2) ** 2
            constraints.append(X[:, k + 1] - step(X[:, k], U[:, k], kappas[k]))
        cost += c.terminal_weight * state_cost(X[:, n], kappas[n - 1])
        w = ca.vertcat(ca.reshape(X, -1, 1), ca.reshape(U, -1, 1))
        self.solver = ca.nlpsol(
            "mpc",
            "sqpmethod",
            {"x": w, "p": P, "f": cost, "g": ca.vertcat(*constraints)},
            {
                "qpsol": "qrqp",
                "qpsol_options": {
                    "print_iter": False,
                    "print_header": False,
                    "error_on_fail": False,
                },
                "max_iter": c.max_iterations,
                "print_header": False,
                "print_iteration": False,
                "print_status": False,
                "print_time": False,
                "error_on_fail": False,
            },
        )
        big = 1e3
        lo_x = [-big, -math.pi, -bicycle.max_steer_rad, 0.0]
        hi_x = [big, math.pi, bicycle.max_steer_rad, bicycle.max_speed_mps]
        lo_u = [-bicycle.max_steer_rate_radps, -bicycle.max_decel_mps2]
        hi_u = [bicycle.max_steer_rate_radps, bicycle.max_accel_mps2]
        self.lbw = np.concatenate([np.tile(lo_x, n + 1), np.tile(lo_u, n)])
        self.ubw = np.concatenate([np.tile(hi_x, n + 1), np.tile(hi_u, n)])
        self.n_g = 4 * (n + 1)
        self.n = n


@dataclass(frozen=True)
class Plan:
    """One solve: start time, the planned states (N+1, 4) and inputs (N, 2), whether the
    solver reported success, and its wall time (s)."""

    t_s: float
    states: np.ndarray
    inputs: np.ndarray
    success: bool
    solve_s: float


@dataclass
class MpcController:
    """Drop-in for ``TrackingController``: :meth:`command` at every integration step,
    re-planning every ``config.step_s``; :meth:`set_quality` with each estimate's quality.
    ``solve_times_s`` keeps every solve's wall time (``solve_cpu_s`` its CPU time: the
    wall time less what other processes took of the core), ``failed_solves`` counts the solves
    the SQP did not finish (their last iterate is used: it is within the bounds)."""

    path: Path
    config: MpcConfig
    bicycle: BicycleConfig
    quality: LocalizationQuality | None = None
    solve_times_s: list[float] = field(default_factory=list)
    solve_cpu_s: list[float] = field(default_factory=list)
    failed_solves: int = 0
    _problem: _Problem = field(init=False)
    _hint: int = field(init=False, default=0)
    _plan: Plan | None = field(init=False, default=None)
    _warm: tuple | None = field(init=False, default=None)
    _last_steer_rad: float = field(init=False, default=0.0)

    def __post_init__(self) -> None:
        self._problem = _Problem(self.config, self.bicycle)

    def set_quality(self, quality: LocalizationQuality | None) -> None:
        """The localization's latest quality (used from the next solve on)."""
        self.quality = quality

    def error(self, x_m: float, y_m: float, yaw_rad: float) -> TrackingError:
        err = tracking_error(self.path, x_m, y_m, yaw_rad, self._hint)
        self._hint = err.index
        return err

    def command(
        self, t_s: float, x_m: float, y_m: float, yaw_rad: float, speed_mps: float, dt_s: float
    ) -> tuple[Command, TrackingError]:
        """The command at ``t_s`` for a believed rear-axle pose and measured speed."""
        err = self.error(x_m, y_m, yaw_rad)
        plan = self._plan
        if plan is None or t_s - plan.t_s >= self.config.step_s - 1e-9:
            plan = self._solve(t_s, err, speed_mps)
        tau = min(max(t_s - plan.t_s, 0.0), self.config.step_s)
        k = min(int(tau / self.config.step_s), len(plan.inputs) - 1)
        rate, accel = plan.inputs[k]
        steer = plan.states[k, 2] + rate * (tau - k * self.config.step_s)
        steer = float(np.clip(steer, -self.bicycle.max_steer_rad, self.bicycle.max_steer_rad))
        self._last_steer_rad = steer
        return Command(steer_rad=steer, accel_mps2=float(accel)), err

    @property
    def at_end(self) -> bool:
        return self._hint >= len(self.path.s_m) - 2

    @property
    def last_plan(self) -> Plan | None:
        return self._plan

    def _curvatures(self, err: TrackingError) -> np.ndarray:
        """(N,) the path's curvature where the vehicle is planned to be at each step."""
        c, n = self.config, self.config.steps
        if self._plan is not None:
            v = self._plan.states[1:, 3]  # the previous plan's speeds, one step on
        else:
            v = np.full(n, c.reference_speed_mps)
        s0 = self.path.s_m[err.index]
        s = s0 + np.concatenate([[0.0], np.cumsum(v[:-1] * c.step_s)]) + 0.5 * v * c.step_s
        return np.interp(s, self.path.s_m, self.path.curvature)

    def _solve(self, t_s: float, err: TrackingError, speed_mps: float) -> Plan:
        c, prob, n = self.config, self._problem, self.config.steps
        x0 = np.array([err.lateral_m, err.heading_rad, self._last_steer_rad, speed_mps])
        kappas = self._curvatures(err)
        p = np.concatenate([x0, kappas, [c.reference_speed_mps, view_weight(self.quality, c)]])
        if self._warm is None:
            states = np.tile(x0, (n + 1, 1))
            states[:, 3] = np.linspace(speed_mps, c.reference_speed_mps, n + 1)
            w0 = np.concatenate([states.ravel(), np.zeros(2 * n)])
            lam_x0, lam_g0 = np.zeros(len(w0)), np.zeros(prob.n_g)
        else:
            w0, lam_x0, lam_g0 = self._warm
            w0 = w0.copy()
            w0[:4] = x0
        started, started_cpu = time.perf_counter(), time.thread_time()
        out = prob.solver(
            x0=w0, p=p, lbx=prob.lbw, ubx=prob.ubw, lbg=0.0, ubg=0.0, lam_x0=lam_x0, lam_g0=lam_g0
        )
        solve_s = time.perf_counter() - started
        self.solve_cpu_s.append(time.thread_time() - started_cpu)
        success = bool(prob.solver.stats().get("success", False))
        w = np.asarray(out["x"]).ravel()
        if not np.all(np.isfinite(w)):
            raise InvalidInputError(f"the MPC solver returned non-finite values at t={t_s:.3f} s")
        states = w[: 4 * (n + 1)].reshape(n + 1, 4)
        inputs = w[4 * (n + 1) :].reshape(n, 2)
        # Warm start of the next solve: this plan shifted by one step.
        shifted_states = np.vstack([states[1:], states[-1:]])
        shifted_inputs = np.vstack([inputs[1:], inputs[-1:]])
        self._warm = (
            np.concatenate([shifted_states.ravel(), shifted_inputs.ravel()]),
            np.asarray(out["lam_x"]).ravel(),
            np.asarray(out["lam_g"]).ravel(),
        )
        self.solve_times_s.append(solve_s)
        self.failed_solves += not success
        self._plan = Plan(t_s, states, inputs, success, solve_s)
        return self._plan

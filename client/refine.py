"""A Gaussian filter riding on the particle filter's main mode: the reported pose.

The particle filter (docs/method.md sections 7-8) finds the right place and keeps it: a
mixture over the frame's hypotheses, heavy motion noise and roughening make it robust to
wrong hypotheses and to a start tens of metres off. The same choices make it imprecise
at the centimetre scale: each frame's likelihood is a sum of sharp components, one per
hypothesis, and the broad motion noise forgets the previous frames, so its mode follows
the current frame's hypotheses instead of averaging them over time.

This filter is an extended Kalman filter on (X m, Y m, psi rad, k, b rad, g rad/s): k the
speed signal's scale factor (true speed = k x measured: a wheel's radius is known to a
percent or two, and a 1 % scale error is 9 mm per 0.1 s step at 9 m/s, as large as a
hypothesis's error), b the heading the map's hypotheses give minus the direction the car
drives in, g the yaw-rate signal's bias (true yaw rate = measured - g: an automotive MEMS
gyro's offset of a tenth of a degree per second, the sim's 0.002 rad/s, turns the heading
by 0.3 deg in a 3 s stretch without hypotheses, and a 0.3 deg heading error drifts 5 cm
sideways per second at 9 m/s). It predicts with the measured speed and yaw rate (white
noise of the stated size, propagated through the motion model's Jacobian) and corrects
with the frame's hypotheses under the measurement model's own per-hypothesis Gaussians
(bias-corrected pose and covariance), each gated by its Mahalanobis distance and by the
restart tolerances (a hypothesis metres off with a covariance of metres passes a
Mahalanobis gate, and turns the heading by the tenths of a degree its own heading error
carries through the correlations). It does not decide where
the vehicle is: it starts from the particles' mode and covariance, and starts over from
them whenever the two disagree beyond ``reset_position_m`` / ``reset_yaw_rad`` (a
re-seed, a jump the particles made on evidence this filter gated out), or beyond both
spreads for ``restart_after_frames`` frames in a row (the particles follow a few frames
that agree on one wrong pose; this filter waits them out). k, b and g belong
to the vehicle and its map, not to the place: they survive a restart.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from monoloc.client.motion import advance
from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import wrap_angle
from monoloc.core.measurement import Hypotheses, MeasurementModel
from monoloc.core.mounting import PlanarMount


@dataclass(frozen=True)
class RefineConfig:
    """Settings of the mode's Gaussian filter.

    speed_noise_mps / yaw_rate_noise_radps: 1 sigma white noise of the measured signals
    per step (twice the sim's recording errors, which also have a yaw-rate bias).
    position_noise_m: 1 sigma per step of what the motion model does not say (tyre slip,
    the lever arm's error). speed_scale_std: prior 1 sigma of k around 1;
    speed_scale_walk: its random walk per step; speed_scale_bounds: k is clipped to them.
    heading_offset_std_rad: prior 1 sigma of b, the heading the map's hypotheses give minus
    the direction the car drives in (a map whose LiDAR-camera calibration is off by 0.2
    deg gives headings off by about that; 0 keeps b at 0); heading_offset_walk_rad: its
    random walk per step. yaw_rate_bias_std_radps: prior 1 sigma of g, the yaw-rate
    signal's bias (0 keeps g at 0); yaw_rate_bias_walk_radps: its random walk per step.
    gate_mahalanobis_sq: a hypothesis further than this (squared, 3 dof; 16: P = 0.1 %)
    from the prediction is not used, nor one further than the restart tolerances
    ``reset_position_m`` / ``reset_yaw_rad``.
    restart_mahalanobis_sq: the filter also starts over from the particles' mode when the
    two are further apart than this (squared, 3 dof) under the sum of this filter's pose
    covariance and the particles' spread: started from a mode on a wrong hypothesis with
    the particles' tight spread there, it gates out the right hypotheses that move the
    particles, and when it takes one at last, the heading jump goes into b and g (None:
    the tolerances alone). restart_after_frames: a disagreement within the restart
    tolerances restarts the filter only once it has lasted this many frames in a row
    (1: at once); beyond the tolerances it restarts at once. Why: the particles follow
    a few frames whose every hypothesis agrees on one wrong pose (a parked car that
    moved since the map was made pulls every entry the same way); restarting on them
    takes the reported pose along, and then gates out the right poses that follow.
    """

    speed_noise_mps: float = 0.1
    yaw_rate_noise_radps: float = 0.01
    position_noise_m: float = 0.002
    speed_scale_std: float = 0.02
    speed_scale_walk: float = 1e-4
    speed_scale_bounds: tuple[float, float] = (0.9, 1.1)
    heading_offset_std_rad: float = math.radians(0.5)
    heading_offset_walk_rad: float = math.radians(0.002)
    yaw_rate_bias_std_radps: float = 0.005
    yaw_rate_bias_walk_radps: float = 1e-5
    gate_mahalanobis_sq: float = 16.0
    reset_position_m: float = 0.5
    reset_yaw_rad: float = math.radians(2.0)
    restart_mahalanobis_sq: float | None = 16.0
    restart_after_frames: int = 20

    def __post_init__(self) -> None:
        lo, hi = self.speed_scale_bounds
        positive = (
            self.speed_noise_mps,
            self.yaw_rate_noise_radps,
            self.speed_scale_std,
            self.gate_mahalanobis_sq,
            self.restart_mahalanobis_sq or 1.0,
            self.reset_position_m,
            self.reset_yaw_rad,
        )
        non_negative = (
            self.position_noise_m,
            self.speed_scale_walk,
            self.heading_offset_std_rad,
            self.heading_offset_walk_rad,
            self.yaw_rate_bias_std_radps,
            self.yaw_rate_bias_walk_radps,
        )
        if min(positive) <= 0 or min(non_negative) < 0:
            raise InvalidInputError(f"refinement noises and gates must be positive: {self}")
        if self.restart_after_frames < 1:
            raise InvalidInputError(
                f"restart_after_frames must be >= 1, got {self.restart_after_frames}"
            )
        if not 0 < lo <= 1 <= hi:
            raise InvalidInputError(f"speed_scale_bounds must hold 1, got {(lo, hi)}")


class ModeRefiner:
    """The Gaussian filter's state: mean (6,) (X m, Y m, psi rad, k, b rad, g rad/s) and
    covariance (6, 6). psi is the direction the camera drives in; the pose it reports and
    that the hypotheses measure has heading psi + b; the yaw rate it integrates is the
    measured one minus g."""

    N_STATE = 6

    def __init__(self, config: RefineConfig) -> None:
        self.config = config
        self.state: np.ndarray | None = None
        self.covariance = np.zeros((self.N_STATE, self.N_STATE))
        # the vehicle's own terms (k, b, g) and their covariance, kept across restarts
        self._vehicle = np.array([1.0, 0.0, 0.0])
        self._vehicle_cov = np.diag(
            [
                config.speed_scale_std**2,
                config.heading_offset_std_rad**2,
                config.yaw_rate_bias_std_radps**2,
            ]
        )
        self.n_restarts = 0

    @property
    def active(self) -> bool:
        return self.state is not None

    @property
    def pose_world(self) -> np.ndarray:
        """(3,) planar pose (X, Y, heading): the heading is the hypotheses', psi + b."""
        if self.state is None:
            raise InvalidInputError("the refinement has not started")
        x, y, psi, _, b, _ = self.state
        return np.array([x, y, float(wrap_angle(psi + b))])

    def _vehicle_term(self, index: int) -> float:
        return float(self.state[3 + index] if self.state is not None else self._vehicle[index])

    @property
    def speed_scale(self) -> float:
        """The speed signal's scale factor k as estimated so far."""
        return self._vehicle_term(0)

    @property
    def heading_offset_rad(self) -> float:
        """b as estimated so far."""
        return self._vehicle_term(1)

    @property
    def yaw_rate_bias_radps(self) -> float:
        """g, the yaw-rate signal's bias, as estimated so far."""
        return self._vehicle_term(2)

    def stop(self) -> None:
        """Forget the pose (keep k, b and g): the next start takes the particles'."""
        if self.state is not None:
            self._vehicle = self.state[3:].copy()
            self._vehicle_cov = self.covariance[3:, 3:].copy()
        self.state = None

    def start(self, pose_world: np.ndarray, covariance: np.ndarray) -> None:
        """Start at the pose (3,) with its covariance (3, 3) (the particles' mode and
        spread), keeping k, b and g learnt so far."""
        self.stop()
        pose = np.asarray(pose_world, dtype=np.float64)[:3]
        b = self._vehicle[1]
        self.state = np.array([pose[0], pose[1], float(wrap_angle(pose[2] - b)), *self._vehicle])
        # psi = heading - b: its variance is the heading's plus b's
        n = self.N_STATE
        J = np.eye(n)
        J[2, 4] = -1.0
        full = np.zeros((n, n))
        full[:3, :3] = 0.5 * (covariance + covariance.T)
        full[3:, 3:] = self._vehicle_cov
        self.covariance = J @ full @ J.T
        self.n_restarts += 1

    @property
    def pose_covariance(self) -> np.ndarray:
        """(3, 3) covariance of :attr:`pose_world` (X, Y, psi + b)."""
        H = np.zeros((3, self.N_STATE))
        H[:, :3] = np.eye(3)
        H[2, 4] = 1.0
        return H @ self.covariance @ H.T

    def within_tolerances(self, pose_world: np.ndarray) -> bool:
        """Whether the pose (3,) is within ``reset_position_m`` / ``reset_yaw_rad`` of this
        filter's."""
        diff = np.asarray(pose_world, dtype=np.float64)[:3] - self.pose_world
        return (
            math.hypot(diff[0], diff[1]) <= self.config.reset_position_m
            and abs(float(wrap_angle(diff[2]))) <= self.config.reset_yaw_rad
        )

    def agrees_with(self, pose_world: np.ndarray, covariance: np.ndarray | None = None) -> bool:
        """Whether the pose (3,) is within the restart tolerances of this filter's and,
        with its covariance (3, 3) and ``restart_mahalanobis_sq`` set, within that
        Mahalanobis distance under the sum of the two covariances."""
        mine = self.pose_world
        diff = np.asarray(pose_world, dtype=np.float64)[:3] - mine
        diff[2] = wrap_angle(diff[2])
        if (
            math.hypot(diff[0], diff[1]) > self.config.reset_position_m
            or abs(diff[2]) > self.config.reset_yaw_rad
        ):
            return False
        if covariance is None or self.config.restart_mahalanobis_sq is None:
            return True
        S = self.pose_covariance + 0.5 * (covariance + covariance.T)
        try:
            squared = float(diff @ np.linalg.solve(S, diff))
        except np.linalg.LinAlgError:
            return True
        return squared <= self.config.restart_mahalanobis_sq

    def predict(
        self,
        dt_s: float,
        speed_mps: float,
        yaw_rate_radps: float,
        mount: PlanarMount | float = 0.0,
    ) -> None:
        """One step of the measured signals (the camera at ``mount`` on the vehicle, see
        motion.advance); the covariance through the Jacobians of the motion model in the
        state and in the two signals (forward differences)."""
        if self.state is None or dt_s <= 0:
            return
        cfg = self.config
        eps = np.array([1e-6, 1e-6, 1e-7, 1e-7, 1e-6, 1e-7])  # X, Y, psi, k, speed, yaw rate
        poses = np.repeat(self.state[None, :3], 7, axis=0)
        scale = np.full(7, self.state[3])
        speed = np.full(7, speed_mps, dtype=np.float64)
        yaw_rate = np.full(7, yaw_rate_radps - self.state[5], dtype=np.float64)
        for col in range(3):
            poses[1 + col, col] += eps[col]
        scale[4] += eps[3]
        speed[5] += eps[4]
        yaw_rate[6] += eps[5]
        moved = advance(poses, scale * speed, yaw_rate, dt_s, mount)
        diff = moved[1:] - moved[0]
        diff[:, 2] = wrap_angle(diff[:, 2])
        jac = (diff / eps[:, None]).T  # (3, 6): d pose / d (X, Y, psi, k, speed, yaw rate)
        n = self.N_STATE
        F = np.eye(n)
        F[:3, :4] = jac[:, :4]
        F[:3, 5] = -jac[:, 5]  # the bias is taken off the measured yaw rate
        G = np.zeros((n, 2))
        G[:3] = jac[:, 4:]
        Q = G @ np.diag([cfg.speed_noise_mps**2, cfg.yaw_rate_noise_radps**2]) @ G.T
        Q += np.diag(
            [
                cfg.position_noise_m**2,
                cfg.position_noise_m**2,
                0.0,
                cfg.speed_scale_walk**2,
                cfg.heading_offset_walk_rad**2,
                cfg.yaw_rate_bias_walk_radps**2,
            ]
        )
        self.state = np.array([*moved[0], *self.state[3:]])
        self.state[2] = wrap_angle(self.state[2])
        self.covariance = F @ self.covariance @ F.T + Q

    def correct(self, hypotheses: Hypotheses, model: MeasurementModel) -> int:
        """Correct with one of the frame's hypotheses: the joint pose (the union of its
        entries' inliers), else the per-entry one with the most inliers, the first of
        them within the gate. One, not each in turn: their errors are not independent
        (the entries share the query's keypoints). Returns how many were used (0 or 1)."""
        if self.state is None or len(hypotheses) == 0:
            return 0
        centres, covs = model.hypothesis_gaussians(hypotheses)
        used = 0
        for i in self._order(hypotheses):
            if self._correct_one(centres[i], covs[i]):
                used = 1
                break
        lo, hi = self.config.speed_scale_bounds
        self.state[3] = float(np.clip(self.state[3], lo, hi))
        return used

    def _order(self, hypotheses: Hypotheses) -> np.ndarray:
        """Indices to try: the joint pose first, then by PnP inliers (most first)."""
        n = len(hypotheses)
        inliers = np.zeros(n) if hypotheses.n_inliers is None else hypotheses.n_inliers
        joint = np.zeros(n, dtype=bool) if hypotheses.joint is None else hypotheses.joint
        return np.lexsort((-np.asarray(inliers, dtype=np.float64), ~joint))

    def _correct_one(self, centre_world: np.ndarray, cov: np.ndarray) -> bool:
        """Kalman update with one bias-corrected pose (3,) and covariance (3, 3) (it
        measures X, Y and psi + b), unless it is outside the gate or the restart
        tolerances."""
        n = self.N_STATE
        H = np.zeros((3, n))
        H[:, :3] = np.eye(3)
        H[2, 4] = 1.0
        residual = centre_world - self.pose_world
        residual[2] = wrap_angle(residual[2])
        if (
            math.hypot(residual[0], residual[1]) > self.config.reset_position_m
            or abs(residual[2]) > self.config.reset_yaw_rad
        ):
            return False
        P = self.covariance
        PHt = P @ H.T
        S = H @ PHt + cov
        try:
            solved = np.linalg.solve(S, residual)
        except np.linalg.LinAlgError:
            return False
        if float(residual @ solved) > self.config.gate_mahalanobis_sq:
            return False
        K = np.linalg.solve(S, PHt.T).T  # (6, 3) = P H^T S^-1
        self.state = self.state + K @ residual
        self.state[2] = wrap_angle(self.state[2])
        IKH = np.eye(n) - K @ H
        # Joseph form: stays symmetric and positive with a nearly singular gain
        self.covariance = IKH @ P @ IKH.T + K @ cov @ K.T
        return True

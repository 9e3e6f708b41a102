"""The errors a real recording carries. The world is rendered from the true values; the
files carry the measured ones.

``RecordingErrors()`` is realistic and the default; ``RecordingErrors.none()`` makes the
written geometry exact (tests that check geometry use it; ``bench/accuracy.py`` uses it
for the error floor). Where each default comes from: ``docs/sim.md``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.sim.vehicle import _rpy


@dataclass(frozen=True)
class RecordingErrors:
    """Each error is off when its size is 0 (or the flag False). Defaults: an RTK
    GNSS/INS of the OXTS RT3000 class in city streets, a target-calibrated LiDAR, a
    camera not triggered by the LiDAR (sources and figures: docs/sim.md).

    Ground-truth poses (map and query runs alike, each run its own draw), first-order
    Gauss-Markov errors with correlation time ``pose_error_time_s`` (20 s: they wander
    along the route, they are not white): ``pose_error_m`` horizontal RMS (0.05 m; RT3000
    RTK 0.02 m 1 sigma in open sky, worse between buildings), ``pose_vertical_error_m``
    (0.03 m), ``pose_yaw_error_rad`` (0.1 deg 1 sigma, dual-antenna heading),
    ``pose_tilt_error_rad`` roll and pitch each (0.03 deg 1 sigma). The INS smooths them
    (``pose_error_smoothing_s``, 1 s: a first-order low-pass): from one frame to the next
    the error moves by about a millimetre, not by the 5 mm a first-order process of that
    size and time constant moves in 0.1 s, which would be a 0.05 m/s rate error against
    the RT3000's 0.05 km/h (0.014 m/s) RMS velocity accuracy.
    ``pose_frame_error_m``: horizontal RMS of a further error drawn anew for every frame
    (white, uncorrelated between neighbouring frames; 0, off, by default): what a
    pose source that is not smoothed frame to frame adds, e.g. GNSS multipath jumps or a
    ground truth refined per frame (docs/sim.md; issue 47's decimetre lead).

    LiDAR: ``lidar_motion_distortion``: columns fire over the 0.1 s sweep while the car
    moves, points not compensated. ``lidar_sync_offset_s``: the camera is not triggered
    by the LiDAR: the instant the head faces forward is off the exposure by a run's own
    offset, uniform in +-0.01 s (36 deg of head rotation at 10 Hz), plus
    ``lidar_sync_jitter_s`` (0.002 s, 1 sigma) per frame. ``calib_translation_m`` /
    ``calib_rotation_rad``: size of the error of a run's written LiDAR-to-camera
    calibration (0.02 m, 0.2 deg: target-based calibration).

    Stereo: ``stereo_disparity_error_px``: 1 sigma of a run's disparity offset, the right
    image written shifted horizontally by the run's own draw (a residual of the stereo
    rectification: the two principal points off against the written calibration), so the
    depth a map computes from the pair is off by z^2 / (f B) times the offset, growing
    with the square of the depth (0, off, by default; docs/sim.md).

    Camera: ``exposure_bias_ev``: 1 sigma of a run's auto-exposure offset (0.5 EV);
    ``material_gain``: 1 sigma (log) of a run's per-material gray-level change (0.1: a
    mono sensor under another illuminant colour sees coloured materials at other relative
    gray levels); ``sensor_noise``: shot/read noise on or off.

    Vehicle signals: ``speed_*``, ``yaw_rate_*`` (scale factor, bias, white noise).
    """

    lidar_motion_distortion: bool = True
    lidar_sync_offset_s: float = 0.01
    lidar_sync_jitter_s: float = 0.002
    calib_translation_m: float = 0.02
    calib_rotation_rad: float = math.radians(0.2)
    stereo_disparity_error_px: float = 0.0
    pose_error_m: float = 0.05
    pose_vertical_error_m: float = 0.03
    pose_yaw_error_rad: float = math.radians(0.1)
    pose_tilt_error_rad: float = math.radians(0.03)
    pose_error_time_s: float = 20.0
    pose_error_smoothing_s: float = 1.0
    pose_frame_error_m: float = 0.0
    speed_scale_error: float = 0.01
    speed_bias_mps: float = 0.02
    speed_noise_mps: float = 0.05
    yaw_rate_bias_radps: float = 0.002
    yaw_rate_noise_radps: float = 0.005
    exposure_bias_ev: float = 0.5
    material_gain: float = 0.1
    sensor_noise: bool = True

    @classmethod
    def none(cls) -> RecordingErrors:
        """Exact geometry and signals (camera noise and exposure changes off too)."""
        return cls(
            lidar_motion_distortion=False,
            lidar_sync_offset_s=0.0,
            lidar_sync_jitter_s=0.0,
            calib_translation_m=0.0,
            calib_rotation_rad=0.0,
            stereo_disparity_error_px=0.0,
            pose_error_m=0.0,
            pose_vertical_error_m=0.0,
            pose_yaw_error_rad=0.0,
            pose_tilt_error_rad=0.0,
            pose_frame_error_m=0.0,
            speed_scale_error=0.0,
            speed_bias_mps=0.0,
            speed_noise_mps=0.0,
            yaw_rate_bias_radps=0.0,
            yaw_rate_noise_radps=0.0,
            exposure_bias_ev=0.0,
            material_gain=0.0,
            sensor_noise=False,
        )

    @classmethod
    def only(cls, *groups: str) -> RecordingErrors:
        """The named groups of errors (``ERROR_GROUPS``: pose, calibration, lidar_timing,
        signals, camera) at their defaults, every other error off: what each costs
        (``bench/error_split.py``). ``only()`` is ``none()``; all five groups are the
        defaults."""
        unknown = [g for g in groups if g not in ERROR_GROUPS]
        if unknown:
            raise InvalidInputError(
                f"unknown recording error groups {unknown}; use some of {list(ERROR_GROUPS)}"
            )
        on = cls()
        names = [name for g in groups for name in ERROR_GROUPS[g]]
        return replace(cls.none(), **{name: getattr(on, name) for name in names})

    def to_dict(self) -> dict:
        return asdict(self)


ERROR_GROUPS: dict[str, tuple[str, ...]] = {
    "pose": (
        "pose_error_m",
        "pose_vertical_error_m",
        "pose_yaw_error_rad",
        "pose_tilt_error_rad",
        "pose_frame_error_m",
    ),
    "calibration": ("calib_translation_m", "calib_rotation_rad", "stereo_disparity_error_px"),
    "lidar_timing": ("lidar_motion_distortion", "lidar_sync_offset_s", "lidar_sync_jitter_s"),
    "signals": (
        "speed_scale_error",
        "speed_bias_mps",
        "speed_noise_mps",
        "yaw_rate_bias_radps",
        "yaw_rate_noise_radps",
    ),
    "camera": ("exposure_bias_ev", "material_gain", "sensor_noise"),
}
"""``RecordingErrors``' fields by where the error comes from: every error's size in one group
(the pose errors' time constants, ``pose_error_time_s`` and ``pose_error_smoothing_s``, shape
the pose errors and stay as they are)."""


def perturb_calibration(
    T_cam_from_lidar: np.ndarray, errors: RecordingErrors, rng: np.random.Generator
) -> np.ndarray:
    """The calibration a recording would write: the true one off by a random
    translation of norm ``calib_translation_m`` and rotation of ``calib_rotation_rad``."""
    direction = rng.standard_normal(3)
    direction /= np.linalg.norm(direction)
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    angle = errors.calib_rotation_rad
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R_err = np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K
    T = np.eye(4)
    T[:3, :3] = R_err @ T_cam_from_lidar[:3, :3]
    T[:3, 3] = T_cam_from_lidar[:3, 3] + errors.calib_translation_m * direction
    return T


def smooth_random(
    times_s: np.ndarray,
    sigma: float,
    time_constant_s: float,
    rng: np.random.Generator,
    smoothing_s: float = 0.0,
) -> np.ndarray:
    """(n,) zero-mean Gauss-Markov process of standard deviation ``sigma`` sampled at
    ``times_s`` (first-order, correlation time ``time_constant_s``), passed through a
    first-order low-pass of time constant ``smoothing_s`` (0: none) and scaled back to
    ``sigma``. The first-order process alone moves by sigma sqrt(2 dt / tau) between
    samples however close they are (it has no rate); the low-pass gives it a finite rate
    of about sigma / sqrt(tau * smoothing_s) RMS, as an INS's error has."""
    n = len(times_s)
    out = np.zeros(n)
    if sigma <= 0 or n == 0:
        return out
    out[0] = sigma * rng.standard_normal()
    for k in range(1, n):
        a = math.exp(-(times_s[k] - times_s[k - 1]) / time_constant_s)
        out[k] = a * out[k - 1] + sigma * math.sqrt(1 - a * a) * rng.standard_normal()
    if smoothing_s <= 0:
        return out
    smooth = np.empty(n)
    smooth[0] = out[0]
    for k in range(1, n):
        b = math.exp(-(times_s[k] - times_s[k - 1]) / smoothing_s)
        smooth[k] = b * smooth[k - 1] + (1.0 - b) * out[k]
    # the stationary variance of the low-passed process is sigma^2 tau / (tau + smoothing)
    return smooth * math.sqrt((time_constant_s + smoothing_s) / time_constant_s)


def apply_pose_errors(
    T_world_from_cam: np.ndarray,
    times_s: np.ndarray,
    errors: RecordingErrors,
    rng: np.random.Generator,
    frame_rng: np.random.Generator | None = None,
) -> np.ndarray:
    """(n, 4, 4) written poses: the true ones (n, 4, 4) with slowly varying horizontal and
    vertical position offsets and small heading, roll and pitch errors (about the
    camera's own centre), plus the white per-frame horizontal error
    (``pose_frame_error_m``) drawn from ``frame_rng`` (its own stream, so turning it on
    leaves every other draw as it was; required when that error is on)."""
    tau, lp = errors.pose_error_time_s, errors.pose_error_smoothing_s
    ex = smooth_random(times_s, errors.pose_error_m / math.sqrt(2), tau, rng, lp)
    ey = smooth_random(times_s, errors.pose_error_m / math.sqrt(2), tau, rng, lp)
    ez = smooth_random(times_s, errors.pose_vertical_error_m, tau, rng, lp)
    eyaw = smooth_random(times_s, errors.pose_yaw_error_rad, tau, rng, lp)
    eroll = smooth_random(times_s, errors.pose_tilt_error_rad, tau, rng, lp)
    epitch = smooth_random(times_s, errors.pose_tilt_error_rad, tau, rng, lp)
    out = np.array(T_world_from_cam, dtype=np.float64, copy=True)
    out[:, :3, :3] = _rpy(eroll, epitch, eyaw) @ out[:, :3, :3]
    out[:, 0, 3] += ex
    out[:, 1, 3] += ey
    out[:, 2, 3] += ez
    if errors.pose_frame_error_m > 0:
        if frame_rng is None:
            raise ValueError("pose_frame_error_m needs frame_rng")
        white = frame_rng.standard_normal((len(out), 2))
        out[:, :2, 3] += errors.pose_frame_error_m / math.sqrt(2) * white
    return out


def measured_signals(
    speed_mps: np.ndarray,
    yaw_rate_radps: np.ndarray,
    errors: RecordingErrors,
    rng: np.random.Generator,
):
    """(speed, yaw_rate) as the car's sensors report them: scale error, bias, noise."""
    scale = 1.0 + errors.speed_scale_error * rng.standard_normal()
    speed = speed_mps * scale + errors.speed_bias_mps * rng.standard_normal()
    speed = speed + errors.speed_noise_mps * rng.standard_normal(len(speed_mps))
    bias = errors.yaw_rate_bias_radps * rng.standard_normal()
    yaw_rate = (
        yaw_rate_radps
        + bias
        + errors.yaw_rate_noise_radps * rng.standard_normal(len(yaw_rate_radps))
    )
    return np.maximum(speed, 0.0), yaw_rate


def lidar_time_offsets_s(
    n_frames: int, errors: RecordingErrors, rng: np.random.Generator
) -> np.ndarray:
    """(n,) time of each frame's sweep centre (head facing forward) minus the camera
    exposure: the run's fixed offset, uniform in +-``lidar_sync_offset_s``, plus white
    jitter of ``lidar_sync_jitter_s``. Zeros when both are 0."""
    offset = rng.uniform(-1.0, 1.0) * errors.lidar_sync_offset_s
    return offset + errors.lidar_sync_jitter_s * rng.standard_normal(n_frames)


def stereo_disparity_offset_px(errors: RecordingErrors, rng: np.random.Generator) -> float:
    """A run's disparity offset in pixels (0 when ``stereo_disparity_error_px`` is 0)."""
    if errors.stereo_disparity_error_px <= 0:
        return 0.0
    return float(errors.stereo_disparity_error_px * rng.standard_normal())


def shift_right_image(image: np.ndarray, offset_px: float) -> np.ndarray:
    """The right image (H, W) uint8 as written under a disparity offset: moved left by
    ``offset_px`` (bilinear, edge pixels repeated), so every disparity x_left - x_right
    measured on the pair grows by ``offset_px``. The image itself when it is 0."""
    if offset_px == 0:
        return image
    import cv2

    shift = np.array([[1.0, 0.0, -offset_px], [0.0, 1.0, 0.0]])
    size = (image.shape[1], image.shape[0])
    return cv2.warpAffine(
        image, shift, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )


def exposure_bias_ev(errors: RecordingErrors, rng: np.random.Generator) -> float:
    """A run's auto-exposure offset in EV (0 when ``exposure_bias_ev`` is 0)."""
    return float(errors.exposure_bias_ev * rng.standard_normal())


def material_gains(
    n_textures: int, errors: RecordingErrors, rng: np.random.Generator
) -> np.ndarray | None:
    """(n_textures,) float32 factors on each texture's gray level for one run, log-normal
    with ``material_gain``; None when it is 0. Draws are sequential, so the first m of n
    gains are the gains of m textures."""
    if errors.material_gain <= 0:
        return None
    return np.exp(errors.material_gain * rng.standard_normal(n_textures)).astype(np.float32)

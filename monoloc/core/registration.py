"""Registering a run to a map it is added to: the correction of its written positions.

Two recordings of one street disagree by their navigation errors (an RTK GNSS/INS wanders
by centimetres between buildings, by decimetres or more where the sky is hidden), and
the error changes slowly along a run. Entries of a night run added to a day map would
otherwise sit in a frame a few centimetres off the map's, and hypotheses from them
disagree with hypotheses from the map's own entries by that much.

The server localizes frames of the new run against the map as it stands, each near its
written pose; each such frame gives a measured offset (localized minus written position,
world frame). This module turns those offsets into a correction per frame: outliers
removed (median and MAD), then a Gaussian-kernel average over time with a zero-mean
prior of the navigation error's size, so that a frame far in time from any measurement,
or a run with only a few measurements, is corrected little or not at all. Position
only: a heading error of an RTK INS (about 0.1 deg) moves a hypothesis by a few
millimetres at the distances between a query and its entries.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monoloc.core.errors import InvalidInputError


@dataclass(frozen=True)
class RegistrationConfig:
    """How a run added to a map is registered to it.

    prior_std_m: the size of the disagreement expected between two runs' navigation, per
    axis (1 sigma); time_scale_s: how long the disagreement stays about the same (the
    Gauss-Markov correlation time of an INS's error; the kernel's sigma); gate_m: measured
    offsets larger than this are not evidence (a wrong place, not a navigation error);
    outlier_mads: measured offsets further than this many MADs from the median are
    dropped; min_noise_m: the smallest noise assumed for one measured offset; min_frames:
    fewer frames kept than this and the run is not moved (consecutive frames see the same
    entries, so their errors are not independent, and a handful of frames of a night run
    against a day map moved a dev city's night map the wrong way); k: entries
    retrieved per frame; search_radius_m / yaw_tolerance_rad: where around its written
    pose a frame looks; every: measure one frame in ``every``.
    """

    prior_std_m: float = 0.1
    time_scale_s: float = 20.0
    gate_m: float = 1.0
    outlier_mads: float = 3.0
    min_noise_m: float = 0.01
    min_frames: int = 20
    k: int = 10
    search_radius_m: float = 5.0
    yaw_tolerance_rad: float = 0.3
    every: int = 1

    def __post_init__(self) -> None:
        positive = (
            self.prior_std_m,
            self.time_scale_s,
            self.gate_m,
            self.outlier_mads,
            self.min_noise_m,
            self.search_radius_m,
            self.yaw_tolerance_rad,
        )
        if not all(np.isfinite(v) and v > 0 for v in positive):
            raise InvalidInputError(f"RegistrationConfig values must be positive: {self}")
        if self.k < 1 or self.every < 1 or self.min_frames < 1:
            raise InvalidInputError(
                f"RegistrationConfig needs k, every and min_frames >= 1: {self}"
            )


@dataclass(frozen=True)
class RunCorrection:
    """offsets_m (N, 2): world-frame (x, y) to add to each frame's written position;
    measured / used: frames that localized near their written pose / kept after the
    outlier test; noise_m: the spread of one measured offset (MAD-based, per axis)."""

    offsets_m: np.ndarray
    measured: int
    used: int
    noise_m: np.ndarray

    def summary(self) -> dict[str, object]:
        """JSON-ready figures for a job result or a report."""
        norms = np.linalg.norm(self.offsets_m, axis=1) if len(self.offsets_m) else np.zeros(1)
        mean = self.offsets_m.mean(axis=0) if len(self.offsets_m) else np.zeros(2)
        return {
            "frames_measured": self.measured,
            "frames_used": self.used,
            "offset_mean_m": [round(float(v), 4) for v in mean],
            "offset_max_m": round(float(norms.max()), 4),
            "noise_m": [round(float(v), 4) for v in self.noise_m],
        }


def run_correction(
    frame_times_s: np.ndarray,
    measured_times_s: np.ndarray,
    measured_offsets_m: np.ndarray,
    config: RegistrationConfig = RegistrationConfig(),
) -> RunCorrection:
    """Per-frame corrections (N, 2) from measured offsets (M, 2) at times (M,).

    Offsets beyond ``gate_m`` and beyond ``outlier_mads`` MADs of the median (per axis)
    are dropped; fewer than ``min_frames`` left: no correction. With s the measurement
    noise (MAD x 1.4826, at least ``min_noise_m``), w_ij = exp(-(t_i - t_j)^2 / (2 T^2))
    and p = ``prior_std_m``, frame j's correction is
    sum_i w_ij d_i / s^2 / (sum_i w_ij / s^2 + 1 / p^2): the posterior mean of a zero-mean
    Gaussian offset seen through the measurements near it in time.
    """
    times = np.asarray(frame_times_s, dtype=np.float64).reshape(-1)
    t_meas = np.asarray(measured_times_s, dtype=np.float64).reshape(-1)
    d = np.asarray(measured_offsets_m, dtype=np.float64).reshape(-1, 2)
    if len(t_meas) != len(d):
        raise InvalidInputError(f"{len(t_meas)} measurement times for {len(d)} offsets")
    if not (np.all(np.isfinite(times)) and np.all(np.isfinite(t_meas))):
        raise InvalidInputError("frame and measurement times must be finite")
    finite = np.all(np.isfinite(d), axis=1) & (np.linalg.norm(d, axis=1) <= config.gate_m)
    measured = int(finite.sum())
    t_meas, d = t_meas[finite], d[finite]
    noise = np.full(2, config.min_noise_m)
    if len(d) == 0:
        return RunCorrection(np.zeros((len(times), 2)), 0, 0, noise)
    median = np.median(d, axis=0)
    mad = 1.4826 * np.median(np.abs(d - median), axis=0)
    noise = np.maximum(mad, config.min_noise_m)
    keep = np.all(np.abs(d - median) <= config.outlier_mads * noise, axis=1)
    t_meas, d = t_meas[keep], d[keep]
    if len(d) < config.min_frames:
        return RunCorrection(np.zeros((len(times), 2)), measured, len(d), noise)
    w = np.exp(-0.5 * ((times[:, None] - t_meas[None, :]) / config.time_scale_s) ** 2)
    information = w.sum(axis=1)[:, None] / noise**2  # (N, 2)
    pulled = (w @ d) / noise**2
    offsets = pulled / (information + 1.0 / config.prior_std_m**2)
    return RunCorrection(offsets, measured, int(keep.sum()), noise)

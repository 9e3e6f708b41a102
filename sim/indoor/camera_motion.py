"""The colour camera of a moving car, frame after frame: motion blur (the image moves
during the exposure), rolling shutter (rows read one after another while the camera
moves) and an auto-exposure that follows the scene's brightness with a lag.

Both need the camera's previous frame, so a drive keeps a ``CameraState`` (``reset`` at
the start of a drive: the first frame has no blur and exposes at once).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from monoloc.core.camera import CameraIntrinsics


@dataclass(frozen=True)
class MotionBlurConfig:
    """max_exposure_time_s: the exposure time at the auto-exposure's longest setting
    (CameraConfig.max_exposure); the time of a frame is that times its exposure share.
    33 ms: the D435i's RGB sensor (OmniVision OV2740) runs its auto-exposure up to one
    frame time at 30 fps, and indoor lab light keeps it near the top (an assumption of
    this sim; the paper gives no exposure). samples: sub-frames averaged along the image
    motion. enabled False: no blur."""

    enabled: bool = True
    max_exposure_time_s: float = 0.033
    samples: int = 5


@dataclass(frozen=True)
class AutoExposureConfig:
    """time_constant_s: first-order lag of the exposure towards the scene's wanted
    exposure (log domain). 0.3 s (about 5 frames at 15 Hz) is an assumption of this sim,
    the settling of consumer-camera auto-exposure loops over a few to ten frames; 0:
    instantaneous (the former model)."""

    time_constant_s: float = 0.3


@dataclass(frozen=True)
class RollingShutterConfig:
    """readout_s: time from the first row's exposure to the last's; the frame's stamp is
    its middle row's time. The D435i's RGB sensor (OmniVision OV2740) is rolling shutter,
    and its skew scales with the frame time (librealsense issue 3554: read out over most
    of a frame); 25 ms, three quarters of a 30 fps frame, is an assumption within that.
    0: a global shutter."""

    readout_s: float = 0.025


def image_motion_px(
    depth_m: np.ndarray,
    T_prev_from_cur: np.ndarray,
    intrinsics: CameraIntrinsics,
    share: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(du, dv) (H, W) float32 pixels: how far each pixel's scene point moves in the image
    while the camera moves ``share`` of the relative motion ``T_prev_from_cur`` (4, 4;
    camera frames, OpenCV axes) forward in time. Pixels without depth move as if at 10 m."""
    import cv2

    k = intrinsics
    h, w = depth_m.shape
    z = np.where(np.isfinite(depth_m) & (depth_m > 0), depth_m, 10.0).astype(np.float32)
    x = ((np.arange(w, dtype=np.float32) - k.cx) / k.fx)[None, :]
    y = ((np.arange(h, dtype=np.float32) - k.cy) / k.fy)[:, None]
    rotvec, _ = cv2.Rodrigues(np.asarray(T_prev_from_cur[:3, :3], np.float64))
    R_part, _ = cv2.Rodrigues(rotvec * share)
    t_part = np.asarray(T_prev_from_cur[:3, 3], np.float64) * share
    # The camera at the end of the motion share, seen from the current camera: moved by
    # (R_part, t_part); a point P = z (x, y, 1) becomes R_part^T (P - t_part) in it.
    R = R_part.astype(np.float32)
    tx, ty, tz = (np.float32(v) for v in t_part)
    px, py, pz = x * z - tx, y * z - ty, z - tz
    later = [R[0, i] * px + R[1, i] * py + R[2, i] * pz for i in range(3)]
    zl = np.maximum(later[2], np.float32(1e-3))
    du = np.float32(k.fx) * (later[0] / zl - x)
    dv = np.float32(k.fy) * (later[1] / zl - y)
    return du.astype(np.float32), dv.astype(np.float32)


def motion_blur(
    radiance: np.ndarray,
    depth_m: np.ndarray,
    T_prev_from_cur: np.ndarray,
    intrinsics: CameraIntrinsics,
    exposure_share_of_period: float,
    samples: int,
) -> np.ndarray:
    """Radiance (H, W) float32 averaged over the exposure: ``exposure_share_of_period`` of
    the motion between the previous frame and this one (``T_prev_from_cur``, assumed to
    continue at the same rate), centred on the frame's time, in ``samples`` steps."""
    import cv2

    if samples < 2 or exposure_share_of_period <= 0:
        return radiance
    # The motion over the exposure is the same motion forwards (T_cur_from_next ~
    # T_prev_from_cur); sample points along it, from -1/2 to +1/2 of the exposure.
    du, dv = image_motion_px(depth_m, T_prev_from_cur, intrinsics, exposure_share_of_period)
    h, w = radiance.shape
    cols = np.arange(w, dtype=np.float32)[None, :]
    rows = np.arange(h, dtype=np.float32)[:, None]
    acc = np.zeros_like(radiance, dtype=np.float32)
    for s in np.linspace(-0.5, 0.5, samples):
        map_x = (cols + np.float32(s) * du).astype(np.float32)
        map_y = (rows + np.float32(s) * dv).astype(np.float32)
        acc += cv2.remap(radiance, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return acc / np.float32(samples)


def rolling_shutter(
    radiance: np.ndarray,
    depth_m: np.ndarray,
    T_prev_from_cur: np.ndarray,
    intrinsics: CameraIntrinsics,
    readout_share_of_period: float,
) -> np.ndarray:
    """Radiance (H, W) float32 read out row after row: row v is seen
    ``(v / (H - 1) - 1/2) * readout_share_of_period`` of the motion between the previous
    frame and this one (``T_prev_from_cur``, assumed to continue) after the frame's
    time (top rows earlier, bottom rows later)."""
    import cv2

    if readout_share_of_period <= 0:
        return radiance
    du, dv = image_motion_px(depth_m, T_prev_from_cur, intrinsics, readout_share_of_period)
    h, w = radiance.shape
    share = (np.arange(h, dtype=np.float32) / np.float32(max(h - 1, 1)) - 0.5)[:, None]
    map_x = (np.arange(w, dtype=np.float32)[None, :] + share * du).astype(np.float32)
    map_y = (np.arange(h, dtype=np.float32)[:, None] + share * dv).astype(np.float32)
    return cv2.remap(radiance, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


class CameraState:
    """The previous frame of a drive: its camera pose (4, 4) and exposure."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.T_world_from_cam: np.ndarray | None = None
        self.exposure: float | None = None

    def adaptation(self, config: AutoExposureConfig, period_s: float) -> float:
        """The share of the way to the wanted exposure one frame goes (1: at once)."""
        if config.time_constant_s <= 0:
            return 1.0
        return 1.0 - math.exp(-period_s / config.time_constant_s)

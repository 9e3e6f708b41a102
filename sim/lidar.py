"""A 64-beam spinning LiDAR like KITTI's Velodyne HDL-64E, ray cast exactly on the quads.

LiDAR frame: x forward, y left, z up. The head spins clockwise seen from above; column
c (of A per turn) points at azimuth ``pi - 2 pi (c + 0.5) / A`` and fires at
``t_frame + ((c + 0.5) / A - 0.5) * period``: the sweep starts and ends behind the car
and points straight ahead at the frame time (when KITTI's camera is triggered). Each
column is cast from the LiDAR pose at its own firing time, and its points are written
in that pose's frame, not motion-compensated, like KITTI's scans. Pass the same pose for
every column to get an undistorted scan.

Ray casting is exact: every beam is intersected with every candidate quad of its
azimuth range (a compiled loop), nearest front-facing hit wins; alpha-textured quads
(tree crowns, signs) let beams through where transparent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from monoloc.sim.scene import KIND_GLASS, Scene
from monoloc.sim.textures import TextureBank


def hdl64_elevations_deg() -> tuple[float, ...]:
    """The HDL-64E's 64 beam elevations: upper block 32 beams +2 to -8.33 deg, lower
    block 32 beams -8.83 to -24.8 deg."""
    upper = np.linspace(2.0, -8.33, 32)
    lower = np.linspace(-8.83, -24.8, 32)
    return tuple(float(e) for e in np.concatenate([upper, lower]))


@dataclass(frozen=True)
class LidarConfig:
    """azimuth_steps: columns per turn; range limits and noise in metres; period_s: one
    turn; glass_dropout: fraction of returns lost on car windows."""

    elevations_deg: tuple[float, ...] = field(default_factory=hdl64_elevations_deg)
    azimuth_steps: int = 2000
    min_range_m: float = 2.0
    max_range_m: float = 120.0
    range_noise_m: float = 0.02
    period_s: float = 0.1
    glass_dropout: float = 0.5


def column_azimuths_rad(config: LidarConfig) -> np.ndarray:
    """(A,) azimuth of each column in the LiDAR frame."""
    c = np.arange(config.azimuth_steps)
    return np.pi - 2.0 * np.pi * (c + 0.5) / config.azimuth_steps


def firing_times_s(t_frame_s: float, config: LidarConfig) -> np.ndarray:
    """(A,) firing time of each column of the sweep centred on ``t_frame_s``."""
    c = np.arange(config.azimuth_steps)
    return t_frame_s + ((c + 0.5) / config.azimuth_steps - 0.5) * config.period_s


def beam_directions(config: LidarConfig) -> np.ndarray:
    """(A, B, 3) unit ray directions in the LiDAR frame."""
    az = column_azimuths_rad(config)[:, None]
    el = np.radians(np.asarray(config.elevations_deg))[None, :]
    return np.stack(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) * np.ones_like(az)], axis=-1
    )


def scan(
    scene: Scene,
    T_world_from_lidar: np.ndarray,
    config: LidarConfig,
    rng: np.random.Generator,
    bank: TextureBank | None = None,
) -> np.ndarray:
    """One sweep. ``T_world_from_lidar``: (4, 4), or (A, 4, 4) one pose per column at its
    firing time (motion distortion). Returns (N, 4) float32 points x, y, z, reflectance in
    the LiDAR frame (of each column's firing time), ordered by beam then column.
    ``bank`` is needed only if the scene has alpha-textured quads."""
    A = config.azimuth_steps
    T = np.asarray(T_world_from_lidar, dtype=np.float64)
    if T.ndim == 2:
        T = np.broadcast_to(T, (A, 4, 4))
    dirs_lidar = beam_directions(config)
    origins = T[:, :3, 3].copy()
    dirs_world = np.einsum("cij,cbj->cbi", T[:, :3, :3], dirs_lidar)
    cand, col_lo, col_hi = _candidates(scene, T, config)
    q = scene.quads
    alpha = _alpha_atlas(scene, cand, bank)
    ranges, ids = _cast_kernel()(
        origins,
        np.ascontiguousarray(dirs_world),
        q.origin[cand],
        q.axis_u[cand],
        q.axis_v[cand],
        q.normal[cand],
        q.size_u[cand],
        q.size_v[cand],
        q.two_sided[cand],
        col_lo,
        col_hi,
        *alpha,
        config.min_range_m,
        config.max_range_m,
    )
    hit = ids >= 0
    quad = np.where(hit, cand[np.maximum(ids, 0)], -1)
    kinds = q.kind[np.maximum(quad, 0)]
    drop = (kinds == KIND_GLASS) & (rng.random(hit.shape) < config.glass_dropout)
    hit &= ~drop
    noisy = ranges + config.range_noise_m * rng.standard_normal(ranges.shape)
    # Beam-major order, like the rings of a real scan.
    hit_t = hit.T
    pts = (noisy[..., None] * dirs_lidar).transpose(1, 0, 2)[hit_t]
    cos_in = np.abs(np.einsum("cbi,cbi->cb", dirs_world, q.normal[np.maximum(quad, 0)])).T[hit_t]
    refl = q.reflectance[quad.T[hit_t]] * (0.6 + 0.4 * np.sqrt(cos_in))
    refl = np.clip(refl * (1.0 + 0.1 * rng.standard_normal(len(refl))), 0.0, 1.0)
    return np.column_stack([pts, refl]).astype(np.float32)


def _candidates(scene: Scene, T: np.ndarray, config: LidarConfig):
    """Quads within range of the sweep and, for each, the (possibly wrapping) column
    range [lo, hi] whose rays may hit it, padded for the motion during the sweep."""
    q = scene.quads
    A = config.azimuth_steps
    mid = T[A // 2]
    o = mid[:3, 3]
    travel = float(np.max(np.linalg.norm(T[:, :3, 3] - o, axis=1)))
    # Exact distance from the sweep centre to each rectangle.
    rel = o - q.origin
    s = np.clip(np.einsum("ij,ij->i", rel, q.axis_u), 0, q.size_u)
    t = np.clip(np.einsum("ij,ij->i", rel, q.axis_v), 0, q.size_v)
    nearest = q.origin + s[:, None] * q.axis_u + t[:, None] * q.axis_v
    dist = np.linalg.norm(nearest - o, axis=1)
    cand = np.flatnonzero(dist <= config.max_range_m + travel)
    corners = q.corners()[cand] - o
    yaw_mid = math.atan2(mid[1, 0], mid[0, 0])
    az = np.arctan2(corners[..., 1], corners[..., 0]) - yaw_mid
    ref = az[:, :1]
    rel_az = (az - ref + np.pi) % (2 * np.pi) - np.pi
    lo_az = ref[:, 0] + rel_az.min(axis=1)
    hi_az = ref[:, 0] + rel_az.max(axis=1)
    # Yaw change of the head frame over the sweep, and parallax of the moving origin.
    yaws = np.arctan2(T[:, 1, 0], T[:, 0, 0])
    yaw_drift = float(np.max(np.abs((yaws - yaw_mid + np.pi) % (2 * np.pi) - np.pi)))
    parallax = np.arctan2(travel, np.maximum(dist[cand], 1e-3))
    pad = yaw_drift + parallax + 2.0 * (2 * np.pi / A)
    # Column index is decreasing in azimuth: c = (pi - az) / (2 pi) * A - 0.5.
    col_lo = np.floor((np.pi - (hi_az + pad)) / (2 * np.pi) * A - 0.5).astype(np.int64)
    col_hi = np.ceil((np.pi - (lo_az - pad)) / (2 * np.pi) * A - 0.5).astype(np.int64)
    full = (hi_az - lo_az + 2 * pad >= np.pi) | (dist[cand] < 3.0 + travel)
    col_lo = np.where(full, 0, col_lo)
    col_hi = np.where(full, A - 1, col_hi)
    return cand, col_lo, col_hi


def _alpha_atlas(scene: Scene, cand: np.ndarray, bank: TextureBank | None):
    """Alpha masks of the candidate quads that have one, packed for the kernel:
    (offset (M,) int64, -1 if opaque; width, ppm, offset_x, offset_y per quad; atlas)."""
    q = scene.quads
    m = len(cand)
    offset = np.full(m, -1, np.int64)
    width = np.zeros(m, np.int64)
    height = np.zeros(m, np.int64)
    ppm = q.texels_per_m[cand].astype(np.float64)
    tex_off = q.tex_offset_px[cand].astype(np.float64)
    chunks: list[np.ndarray] = []
    pos = 0
    if bank is not None:
        seen: dict[int, int] = {}
        for k, tex in enumerate(q.texture[cand]):
            spec = scene.textures[tex]
            if spec.kind not in ("foliage", "sign"):
                continue
            if tex not in seen:
                alpha = bank.layers(spec).alpha
                if alpha is None:
                    continue
                seen[tex] = pos
                chunks.append(alpha.ravel())
                pos += alpha.size
            offset[k] = seen[tex]
            width[k], height[k] = spec.width_px, spec.height_px
    atlas = np.concatenate(chunks) if chunks else np.zeros(1, np.uint8)
    return offset, width, height, ppm, tex_off, atlas


_KERNEL = None


def _cast_kernel():
    """The compiled ray-casting loop (numba, compiled on first use and cached on disk)."""
    global _KERNEL
    if _KERNEL is None:
        from monoloc.sim._lidar_kernel import cast

        _KERNEL = cast
    return _KERNEL

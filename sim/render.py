"""Rasterise a scene of textured planar quads for a pinhole camera.

A planar quad maps to the image by a homography, so drawing it is one
``cv2.warpPerspective`` of its texture into the quad's on-screen bounding box, masked by
its projected (near-plane-clipped) polygon. Its depth is analytic: on a plane, 1/z is
affine in pixel coordinates, so the z-buffer holds exact inverse depths. Quads are drawn
front to back and a quad whose bounding box is already covered by nearer surfaces is
skipped. Textures come from a mip pyramid, one level per quad chosen from its on-screen
texel footprint, so distant facades do not alias.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.geometry import invert_rigid
from monoloc.sim.scene import Scene
from monoloc.sim.textures import TextureBank


@dataclass(frozen=True)
class RenderConfig:
    """near_m: near clipping plane; max_range_m: quads farther than this are not drawn;
    mip_bias: added to log2(texels per pixel) before choosing the pyramid level (positive
    blurs, negative sharpens and aliases)."""

    near_m: float = 0.2
    max_range_m: float = 150.0
    mip_bias: float = 0.0


@dataclass
class Raster:
    """Rendered buffers, all (H, W): albedo uint8 (None if untextured), emission uint8
    (None unless night), inv_depth float32 (1/z in 1/m, 0 where nothing was hit),
    quad_id int32 (-1 where nothing was hit)."""

    albedo: np.ndarray | None
    emission: np.ndarray | None
    inv_depth: np.ndarray
    quad_id: np.ndarray

    @property
    def depth_m(self) -> np.ndarray:
        """(H, W) float32 z-depth in metres along the optical axis, inf where no surface."""
        with np.errstate(divide="ignore"):
            return np.where(self.inv_depth > 0, 1.0 / self.inv_depth, np.inf).astype(np.float32)


def _clip_near(poly_cam: np.ndarray, near: float) -> np.ndarray:
    """Clip a convex polygon (K, 3) in camera coordinates to z >= near."""
    z = poly_cam[:, 2]
    if np.all(z >= near):
        return poly_cam
    out = []
    k = len(poly_cam)
    for i in range(k):
        a, b = poly_cam[i], poly_cam[(i + 1) % k]
        a_in, b_in = a[2] >= near, b[2] >= near
        if a_in:
            out.append(a)
        if a_in != b_in:
            f = (near - a[2]) / (b[2] - a[2])
            out.append(a + f * (b - a))
    return np.array(out).reshape(-1, 3)


def visible_quads(
    scene: Scene, T_cam_from_world: np.ndarray, intrinsics: CameraIntrinsics, config: RenderConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices of quads that may be visible, front to back, with their camera-frame
    corners (N, 4, 3) and camera-frame normals (N, 3) facing the camera."""
    quads = scene.quads
    R, t = T_cam_from_world[:3, :3], T_cam_from_world[:3, 3]
    # Cheap distance cull on the quads' bounding spheres before transforming corners.
    cam_world = -R.T @ t
    centre = quads.origin + 0.5 * (
        quads.axis_u * quads.size_u[:, None] + quads.axis_v * quads.size_v[:, None]
    )
    radius = 0.5 * np.hypot(quads.size_u, quads.size_v)
    near_enough = np.flatnonzero(
        np.linalg.norm(centre - cam_world, axis=1) - radius <= config.max_range_m
    )
    corners = scene_corners(scene)[near_enough] @ R.T + t
    x, y, z = corners[..., 0], corners[..., 1], corners[..., 2]
    k = intrinsics
    w, h = k.width_px, k.height_px
    keep = np.any(z >= config.near_m, axis=1)
    keep &= ~np.all(k.fx * x + (k.cx + 0.5) * z < 0, axis=1)
    keep &= ~np.all((w - 0.5 - k.cx) * z - k.fx * x < 0, axis=1)
    keep &= ~np.all(k.fy * y + (k.cy + 0.5) * z < 0, axis=1)
    keep &= ~np.all((h - 0.5 - k.cy) * z - k.fy * y < 0, axis=1)
    normals = quads.normal[near_enough] @ R.T
    facing = np.einsum("ij,ij->i", normals, corners[:, 0])  # < 0: front face seen
    keep &= (facing < 0) | quads.two_sided[near_enough]
    sel = np.flatnonzero(keep)
    normals = normals[sel] * np.where(facing[sel] < 0, 1.0, -1.0)[:, None]
    order = np.argsort(np.maximum(z[sel].min(axis=1), config.near_m), kind="stable")
    return near_enough[sel[order]], corners[sel[order]], normals[order]


def scene_corners(scene: Scene) -> np.ndarray:
    """(N, 4, 3) quad corners, cached on the scene."""
    cached = scene.__dict__.get("_corners")
    if cached is None:
        cached = scene.quads.corners()
        object.__setattr__(scene, "_corners", cached)
    return cached


_TILE = 16


def rasterize(
    scene: Scene,
    bank: TextureBank | None,
    T_world_from_cam: np.ndarray,
    intrinsics: CameraIntrinsics,
    config: RenderConfig = RenderConfig(),
    night: bool = False,
) -> Raster:
    """Draw ``scene`` seen from ``T_world_from_cam`` (OpenCV camera axes).

    With ``bank=None`` only depth and quad ids are computed (no textures).
    """
    import cv2

    k = intrinsics
    w, h = k.width_px, k.height_px
    T_cam_from_world = invert_rigid(T_world_from_cam)
    R, t = T_cam_from_world[:3, :3], T_cam_from_world[:3, 3]
    # Inverse depth padded to whole tiles; the padding is +inf so that it never counts
    # as "not yet covered" in the per-tile occlusion test.
    nty, ntx = -(-h // _TILE), -(-w // _TILE)
    inv_full = np.full((nty * _TILE, ntx * _TILE), np.inf, np.float32)
    inv_full[:h, :w] = 0.0
    inv_depth = inv_full[:h, :w]
    tile_min = np.zeros((nty, ntx), np.float32)
    quad_id = np.full((h, w), -1, np.int32)
    textured = bank is not None
    albedo = np.zeros((h, w), np.uint8) if textured else None
    emission = np.zeros((h, w), np.uint8) if (textured and night) else None
    u_all = np.arange(w, dtype=np.float32)
    v_all = np.arange(h, dtype=np.float32)
    indices, corners_cam, normals_cam = visible_quads(scene, T_cam_from_world, k, config)
    if len(indices) == 0:
        return Raster(albedo, emission, inv_depth.copy(), quad_id)
    pre = _precompute(scene, indices, corners_cam, normals_cam, R, t, k, config)
    near = config.near_m
    boxes = pre["box"]
    for n, qi in enumerate(indices.tolist()):
        if pre["clip"][n]:
            poly = _clip_near(corners_cam[n], near)
            if len(poly) < 3:
                continue
            px = poly[:, 0] / poly[:, 2] * k.fx + k.cx
            py = poly[:, 1] / poly[:, 2] * k.fy + k.cy
            x0, x1 = max(0, math.floor(px.min())), min(w, math.floor(px.max()) + 2)
            y0, y1 = max(0, math.floor(py.min())), min(h, math.floor(py.max()) + 2)
            z_min = near
        else:
            px, py = pre["px"][n], pre["py"][n]
            x0, y0, x1, y1, z_min = boxes[n]
        if x1 <= x0 or y1 <= y0:
            continue
        tx0, tx1 = x0 // _TILE, (x1 - 1) // _TILE + 1
        ty0, ty1 = y0 // _TILE, (y1 - 1) // _TILE + 1
        if tile_min[ty0:ty1, tx0:tx1].min() > 1.0 / z_min:
            continue  # fully hidden behind nearer surfaces
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        pts = np.round(np.stack([px - x0, py - y0], axis=1) * 16.0).astype(np.int32)
        cv2.fillConvexPoly(mask, pts, 1, lineType=cv2.LINE_8, shift=4)
        a, b, c = pre["abc"][n]
        inv_z = (a * u_all[x0:x1])[None, :] + (b * v_all[y0:y1] + c)[:, None]
        buf = inv_depth[y0:y1, x0:x1]
        vis = mask.view(bool) & (inv_z > buf)
        if textured:
            warped, has_emission, has_alpha = _warp_texture(
                scene, bank, qi, pre["KPM"][n], pre["level"][n], (x0, y0, x1, y1), night
            )
            if has_alpha:
                vis &= warped[:, :, -1] > 127
            np.copyto(albedo[y0:y1, x0:x1], warped[:, :, 0], where=vis)
            if has_emission:
                np.copyto(emission[y0:y1, x0:x1], warped[:, :, 1], where=vis)
        np.copyto(buf, inv_z, where=vis)
        np.copyto(quad_id[y0:y1, x0:x1], qi, where=vis)
        block = inv_full[ty0 * _TILE : ty1 * _TILE, tx0 * _TILE : tx1 * _TILE]
        tile_min[ty0:ty1, tx0:tx1] = block.reshape(ty1 - ty0, _TILE, tx1 - tx0, _TILE).min(
            axis=(1, 3)
        )
    return Raster(albedo=albedo, emission=emission, inv_depth=inv_depth.copy(), quad_id=quad_id)


def _precompute(scene, indices, corners, normals, R, t, k, config) -> dict[str, np.ndarray]:
    """Per-quad quantities computed for all candidates at once (vectorised)."""
    quads = scene.quads
    z = corners[..., 2]
    zc = np.maximum(z, config.near_m)
    px = corners[..., 0] / zc * k.fx + k.cx
    py = corners[..., 1] / zc * k.fy + k.cy
    # Plane n.X = d in camera coordinates: 1/z = a*u + b*v + c.
    d = np.einsum("ij,ij->i", normals, corners[:, 0])
    a = normals[:, 0] / (k.fx * d)
    b = normals[:, 1] / (k.fy * d)
    c = (normals[:, 2] - normals[:, 0] * k.cx / k.fx - normals[:, 1] * k.cy / k.fy) / d
    abc = np.stack([a, b, c], axis=1).astype(np.float32)
    # Homography texel (level 0) -> image: K [R u, R v, R o + t] M with M texel -> (s, t).
    ppm = quads.texels_per_m[indices]
    off = quads.tex_offset_px[indices]
    P = np.stack(
        [quads.axis_u[indices] @ R.T, quads.axis_v[indices] @ R.T, quads.origin[indices] @ R.T + t],
        axis=2,
    )
    KP = np.einsum("ij,njk->nik", k.K, P)
    M = np.zeros((len(indices), 3, 3))
    M[:, 0, 0] = M[:, 1, 1] = 1.0 / ppm
    M[:, 0, 2] = (0.5 - off[:, 0]) / ppm
    M[:, 1, 2] = (0.5 - off[:, 1]) / ppm
    M[:, 2, 2] = 1.0
    KPM = KP @ M
    # Mip level from the texel footprint of a pixel at a representative depth; the
    # square root of the obliquity is the geometric mean of the two footprint axes.
    z_ref = np.sqrt(zc.min(axis=1) * zc.max(axis=1))
    centre = np.concatenate([corners[..., :2], zc[..., None]], axis=2).mean(axis=1)
    cos_view = np.abs(np.einsum("ij,ij->i", normals, centre)) / np.linalg.norm(centre, axis=1)
    footprint = ppm * z_ref / k.fx / np.sqrt(np.maximum(cos_view, 0.05))
    level = np.floor(np.log2(np.maximum(footprint, 1e-9)) + config.mip_bias)
    level = np.clip(level, 0, _max_levels(scene)[quads.texture[indices]]).astype(np.int32)
    box = (
        np.stack(
            [
                np.clip(np.floor(px.min(axis=1)), 0, k.width_px),
                np.clip(np.floor(py.min(axis=1)), 0, k.height_px),
                np.clip(np.floor(px.max(axis=1)) + 2, 0, k.width_px),
                np.clip(np.floor(py.max(axis=1)) + 2, 0, k.height_px),
            ],
            axis=1,
        )
        .astype(np.int64)
        .tolist()
    )
    zmin = z.min(axis=1).tolist()
    box = [(*b4, zm) for b4, zm in zip(box, zmin, strict=True)]
    return {
        "clip": np.any(z < config.near_m, axis=1).tolist(),
        "px": px,
        "py": py,
        "box": box,
        "abc": abc.tolist(),
        "KPM": KPM,
        "level": level.tolist(),
    }


def _max_levels(scene: Scene) -> np.ndarray:
    cached = scene.__dict__.get("_max_levels")
    if cached is None:
        sizes = np.array([min(s.width_px, s.height_px) for s in scene.textures] or [1])
        cached = np.maximum(0, np.floor(np.log2(np.maximum(sizes // 4, 1)))).astype(np.int32)
        object.__setattr__(scene, "_max_levels", cached)
    return cached


def _warp_texture(scene, bank, qi, KPM, level, box, night):
    """The quad's texture warped into the bounding box ``box`` = (x0, y0, x1, y1):
    ((h, w, C) uint8, has_emission, has_alpha) with channels as ``TextureBank.get``."""
    import cv2

    x0, y0, x1, y1 = box
    spec = scene.textures[scene.quads.texture[qi]]
    layers = bank.layers(spec)
    texture = bank.get(spec, level, night)
    # texel at level L -> texel at level 0: x0 = 2^L x + (2^L - 1) / 2.
    scale = float(1 << level)
    off = (scale - 1.0) / 2.0
    H = KPM.copy()
    H[:, 2] += off * (H[:, 0] + H[:, 1])
    H[:, :2] *= scale
    H[0] -= x0 * H[2]
    H[1] -= y0 * H[2]
    border = cv2.BORDER_WRAP if spec.wrap else cv2.BORDER_REPLICATE
    out = cv2.warpPerspective(
        texture, H, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR, borderMode=border
    )
    if out.ndim == 2:
        out = out[:, :, None]
    return out, night and layers.emission is not None, layers.alpha is not None

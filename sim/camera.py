"""Camera model: lighting of the rasterised scene, exposure, blur, noise, 8-bit output.

``render`` is the pure entry point: scene + pose + intrinsics + lighting -> (image uint8,
depth float32). Radiance is albedo x (sky ambient + sun on the surface's normal) by day;
at night, ambient is faint and surfaces are lit by street lamps and the car's own
headlights, with lit windows and lamp heads glowing. The sensor integrates radiance
with an auto-exposure (time then gain, bounded), adds shot and read noise (amplified by
the gain, so night frames are noisy), blurs slightly (optics), applies vignetting and a
gamma curve, and quantises to uint8.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.sim.lens import lens_remap
from monoloc.sim.render import Raster, RenderConfig, rasterize
from monoloc.sim.scene import KIND_LAMP, KIND_ROAD, Scene
from monoloc.sim.textures import TextureBank

LIGHTINGS = ("day", "dusk", "night")


@dataclass(frozen=True)
class Lighting:
    """Illumination of a run. Radiances are relative (a white wall in sun ~ 1.5).

    sun_azimuth_rad: direction the sunlight comes from, CCW from +x; sun_elevation_rad
    above the horizon. lamp_strength: street lamps (0 = off); window_glow: emission
    scale of lit windows and lamp heads; headlights: the car's own lights (0 = off).
    """

    name: str = "day"
    sun_azimuth_rad: float = 0.8
    sun_elevation_rad: float = 0.7
    sun_strength: float = 1.0
    ambient: float = 0.5
    sky_horizon: float = 1.6
    sky_zenith: float = 1.1
    lamp_strength: float = 0.0
    window_glow: float = 0.0
    headlights: float = 0.0

    @classmethod
    def preset(cls, name: str, rng: np.random.Generator | None = None) -> Lighting:
        """``day``, ``dusk`` or ``night``; with ``rng`` the sun position varies (so two
        day runs are lit from different directions, as at different hours)."""
        if name not in LIGHTINGS:
            raise InvalidInputError(f"unknown lighting {name!r}; use one of {LIGHTINGS}")
        az = float(rng.uniform(-math.pi, math.pi)) if rng is not None else 0.8
        if name == "day":
            el = float(rng.uniform(0.45, 1.0)) if rng is not None else 0.7
            return cls("day", az, el)
        if name == "dusk":
            return cls(
                "dusk",
                az,
                0.03,
                sun_strength=0.02,
                ambient=0.03,
                sky_horizon=0.09,
                sky_zenith=0.04,
                lamp_strength=0.8,
                window_glow=0.6,
                headlights=0.5,
            )
        return cls(
            "night",
            az,
            -0.3,
            sun_strength=0.0,
            ambient=0.0005,
            sky_horizon=0.004,
            sky_zenith=0.0015,
            lamp_strength=1.0,
            window_glow=1.0,
            headlights=1.0,
        )

    @property
    def night(self) -> bool:
        return self.window_glow > 0


@dataclass(frozen=True)
class CameraConfig:
    """Sensor and exposure. Signal is in units of full scale before gamma.

    exposure_target: mean signal the auto-exposure aims for; max_exposure / max_gain
    bound it (at night the image stays darker and gets noisier); exposure_bias_ev: a
    run's offset; shot_noise: variance per unit signal; read_noise: std;
    blur_sigma_px: optics; vignetting: relative fall-off at the corners.
    """

    exposure_target: float = 0.18
    max_exposure: float = 1.0
    max_gain: float = 8.0
    exposure_bias_ev: float = 0.0
    shot_noise: float = 0.0004
    read_noise: float = 0.002
    blur_sigma_px: float = 0.6
    vignetting: float = 0.25
    gamma: float = 2.2
    adaptation: float = 0.5


def lighting_lut(scene: Scene, lighting: Lighting) -> np.ndarray:
    """(N,) radiance multiplier per quad for sun + sky ambient (front face)."""
    n = scene.quads.normal
    ce = math.cos(lighting.sun_elevation_rad)
    sun = np.array(
        [
            ce * math.cos(lighting.sun_azimuth_rad),
            ce * math.sin(lighting.sun_azimuth_rad),
            math.sin(lighting.sun_elevation_rad),
        ]
    )
    direct = np.clip(n @ sun, 0.0, None)
    direct = np.where(scene.quads.two_sided, np.abs(n @ sun), direct)
    sky = 0.75 + 0.25 * n[:, 2]  # up-facing surfaces see more sky
    return (lighting.ambient * sky + lighting.sun_strength * direct).astype(np.float32)


def shade(
    raster: Raster,
    scene: Scene,
    T_world_from_cam: np.ndarray,
    intrinsics: CameraIntrinsics,
    lighting: Lighting,
    material_gain: np.ndarray | None = None,
) -> np.ndarray:
    """Radiance (H, W) float32 of a textured raster under ``lighting``, sky included.
    ``material_gain``: optional (n_textures,) factor on each texture's albedo (a run's
    illuminant colour as a mono sensor sees it)."""
    lut = np.append(lighting_lut(scene, lighting), 0.0)  # index -1 -> sky (set below)
    ids = raster.quad_id
    albedo = raster.albedo.astype(np.float32)
    if material_gain is not None:
        per_quad = np.append(material_gain[scene.quads.texture], 1.0).astype(np.float32)
        albedo = albedo * per_quad[ids]
    radiance = albedo * (lut[ids] / 255.0)
    sky = ids < 0
    if sky.any():
        radiance[sky] = _sky(T_world_from_cam, intrinsics, lighting)[sky]
    if lighting.lamp_strength > 0 or lighting.headlights > 0:
        radiance += (
            albedo
            / 255.0
            * _artificial_light(raster, scene, T_world_from_cam, intrinsics, lighting)
        )
    if raster.emission is not None:
        glow = np.where(scene.quads.kind[ids] == KIND_LAMP, 2.0, 0.12) * lighting.window_glow
        radiance += raster.emission.astype(np.float32) / 255.0 * glow.astype(np.float32)
    return radiance


def _sky(T_world_from_cam, k: CameraIntrinsics, lighting: Lighting) -> np.ndarray:
    """(H, W) sky radiance by ray elevation."""
    R = T_world_from_cam[:3, :3]
    u = (np.arange(k.width_px, dtype=np.float32) - k.cx) / k.fx
    v = (np.arange(k.height_px, dtype=np.float32) - k.cy) / k.fy
    dz = R[2, 0] * u[None, :] + R[2, 1] * v[:, None] + R[2, 2]
    norm = np.sqrt(u[None, :] ** 2 + v[:, None] ** 2 + 1.0)
    sin_el = np.clip(dz / norm, 0.0, 1.0)
    mix = np.sqrt(sin_el)
    return (lighting.sky_horizon * (1 - mix) + lighting.sky_zenith * mix).astype(np.float32)


# Street lamps (lights with a throw direction): a cut-off luminaire throws its light
# down (intensity ~ cos(angle from the nadir)^LAMP_DOWNWARD_POWER, nothing above the
# horizontal) and a house-side shield keeps most of it off the buildings behind it
# (LAMP_HOUSE_SIDE of the road-side intensity). The carriageway is glossy: seen at
# grazing angles it mirrors the lamps ahead in long bright streaks (Blinn-Phong lobe)
# and sends the car's own low beams back towards the camera (asphalt backscatters at
# grazing incidence), so that the lit road, not the facades, fills a night frame.
LAMP_POWER = 4.0
LAMP_DOWNWARD_POWER = 2.0
LAMP_HOUSE_SIDE = 0.2
ROAD_GLOSS = 3.0
ROAD_GLOSS_EXPONENT = 12.0
ROAD_HEADLIGHT_BACKSCATTER = 0.35


def lamp_intensity(to_point: np.ndarray, throw: np.ndarray) -> np.ndarray:
    """Relative intensity (...,) of a lamp towards points ``to_point`` (..., 3) (world
    vectors from the lamp) given its horizontal ``throw`` direction (3,); an all-zero
    ``throw`` is a bare bulb (1 everywhere)."""
    if not np.any(throw):
        return np.ones(to_point.shape[:-1])
    dist = np.linalg.norm(to_point, axis=-1) + 1e-9
    down = np.clip(-to_point[..., 2] / dist, 0.0, 1.0)
    house = np.clip(-(to_point @ throw) / dist, 0.0, 1.0)  # how far behind the lamp
    return down**LAMP_DOWNWARD_POWER * (1.0 - (1.0 - LAMP_HOUSE_SIDE) * house)


def _artificial_light(raster, scene, T_world_from_cam, k, lighting, step: int = 4):
    """(H, W) irradiance from street lamps and headlights, computed every ``step``
    pixels and interpolated (lighting is smooth); on the carriageway it includes the
    lamps' glossy reflection towards the camera."""
    import cv2

    ids = raster.quad_id[::step, ::step]
    inv = raster.inv_depth[::step, ::step]
    hs, ws = ids.shape
    u = (np.arange(ws) * step - k.cx) / k.fx
    v = (np.arange(hs) * step - k.cy) / k.fy
    z = np.where(inv > 0, 1.0 / np.maximum(inv, 1e-6), 0.0)
    pts_cam = np.stack([u[None, :] * z, v[:, None] * z, z], axis=-1)
    R, t = T_world_from_cam[:3, :3], T_world_from_cam[:3, 3]
    pts = pts_cam @ R.T + t
    normals = scene.quads.normal[np.maximum(ids, 0)]
    to_cam = t - pts
    flip = np.einsum("ijk,ijk->ij", normals, to_cam) < 0
    normals = np.where(flip[..., None], -normals, normals)
    view = to_cam / (np.linalg.norm(to_cam, axis=-1, keepdims=True) + 1e-9)
    road = scene.quads.kind[np.maximum(ids, 0)] == KIND_ROAD
    irradiance = np.zeros((hs, ws), np.float64)
    lights = scene.light_positions
    if lighting.lamp_strength > 0 and len(lights):
        near = np.argsort(np.linalg.norm(lights - t, axis=1))[:16]
        for li in near:
            d = lights[li] - pts
            dist2 = np.einsum("ijk,ijk->ij", d, d) + 1.0
            to_light = d / np.sqrt(dist2)[..., None]
            cos_in = np.clip(np.einsum("ijk,ijk->ij", normals, to_light), 0, None)
            throw = scene.light_directions[li]
            if np.any(throw):
                gain = LAMP_POWER * lamp_intensity(-d, throw)
            else:
                gain = 1.5  # a bare bulb (indoor ceiling lamps)
            power = lighting.lamp_strength * scene.light_intensities[li] * gain / dist2
            irradiance += power * cos_in
            if road.any() and np.any(scene.light_directions[li]):
                half = to_light + view
                half /= np.linalg.norm(half, axis=-1, keepdims=True) + 1e-9
                n_h = np.clip(np.einsum("ijk,ijk->ij", normals, half), 0, None)
                irradiance += np.where(road, power * ROAD_GLOSS * n_h**ROAD_GLOSS_EXPONENT, 0.0)
    if lighting.headlights > 0:
        fwd = R[:, 2]
        origin = t + fwd * 0.5 - R[:, 1] * (-0.9)  # ~0.75 m above the road
        d = origin - pts
        dist2 = np.einsum("ijk,ijk->ij", d, d) + 1.0
        dist = np.sqrt(dist2)
        cos_in = np.clip(np.einsum("ijk,ijk->ij", normals, d) / dist, 0, None)
        cone = np.clip((-(d @ fwd) / dist - 0.85) / 0.1, 0, 1)
        beam = lighting.headlights * 4.0 * cone / dist2
        irradiance += beam * np.where(road, np.maximum(cos_in, ROAD_HEADLIGHT_BACKSCATTER), cos_in)
    irradiance[ids < 0] = 0.0
    return cv2.resize(
        irradiance.astype(np.float32), (k.width_px, k.height_px), interpolation=cv2.INTER_LINEAR
    )


def auto_exposure(
    radiance: np.ndarray, config: CameraConfig, previous: float | None = None
) -> float:
    """Exposure x gain (a single factor) that brings the mean signal to the target,
    adapted smoothly from ``previous`` and bounded by max_exposure * max_gain."""
    mean = float(np.mean(radiance[::4, ::4])) + 1e-6
    wanted = config.exposure_target * 2.0**config.exposure_bias_ev / mean
    wanted = min(wanted, config.max_exposure * config.max_gain)
    if previous is None:
        return wanted
    return math.exp(
        (1 - config.adaptation) * math.log(previous) + config.adaptation * math.log(wanted)
    )


def expose(
    radiance: np.ndarray, exposure: float, config: CameraConfig, rng: np.random.Generator
) -> np.ndarray:
    """Radiance (H, W) -> uint8 image: blur, vignetting, noise, gamma, quantisation."""
    import cv2

    h, w = radiance.shape
    signal = radiance
    if config.blur_sigma_px > 0:
        signal = cv2.GaussianBlur(signal, (0, 0), config.blur_sigma_px)
    if config.vignetting > 0:
        yy = (np.arange(h, dtype=np.float32) - h / 2) / (w / 2)
        xx = (np.arange(w, dtype=np.float32) - w / 2) / (w / 2)
        signal = signal * (1.0 - config.vignetting * (xx[None, :] ** 2 + yy[:, None] ** 2))
    gain = max(1.0, exposure / config.max_exposure)
    electrons = np.clip(signal * (exposure / gain), 0.0, 1.0)
    sigma = np.sqrt(config.shot_noise * electrons + config.read_noise**2)
    noisy = electrons + sigma * rng.standard_normal((h, w), dtype=np.float32)
    out = np.clip(noisy * gain, 0.0, 1.0) ** (1.0 / config.gamma)
    return np.clip(out * 255.0 + rng.random((h, w), dtype=np.float32), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class CameraFrame:
    """image (H, W) uint8, depth_m (H, W) float32 (inf: sky), exposure used."""

    image: np.ndarray
    depth_m: np.ndarray
    exposure: float


def render(
    scene: Scene,
    bank: TextureBank,
    T_world_from_cam: np.ndarray,
    intrinsics: CameraIntrinsics,
    lighting: Lighting,
    rng: np.random.Generator,
    config: CameraConfig = CameraConfig(),
    previous_exposure: float | None = None,
    render_config: RenderConfig = RenderConfig(),
    exposure: float | None = None,
    material_gain: np.ndarray | None = None,
) -> CameraFrame:
    """One camera frame of ``scene`` from ``T_world_from_cam`` (OpenCV camera axes).
    ``exposure`` fixes the exposure instead of the auto-exposure (a stereo rig's second
    camera takes the first one's, as synchronised stereo heads do); ``material_gain`` as
    in :func:`shade`. A camera with lens distortion (``intrinsics.distortion``) is
    drawn through its lens (``monoloc.sim.lens``): the scene's radiance on a wider
    pinhole canvas, remapped to the distorted pixels before the sensor (blur, vignetting
    and noise act on the sensor's own pixels); depth stays the z-depth of each pixel's
    ray."""
    lens = None if intrinsics.distortion is None else lens_remap(intrinsics)
    pinhole = intrinsics if lens is None else lens.canvas
    raster = rasterize(scene, bank, T_world_from_cam, pinhole, render_config, night=lighting.night)
    radiance = shade(raster, scene, T_world_from_cam, pinhole, lighting, material_gain)
    depth_m = raster.depth_m
    if lens is not None:
        radiance, depth_m = lens.apply(radiance), lens.apply(depth_m, nearest=True)
    if exposure is None:
        exposure = auto_exposure(radiance, config, previous_exposure)
    image = expose(radiance, exposure, config, rng)
    return CameraFrame(image=image, depth_m=depth_m, exposure=exposure)

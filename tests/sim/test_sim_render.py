import numpy as np
import pytest

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.geometry import T_world_from_cam_planar
from monoloc.sim.render import rasterize
from monoloc.sim.scene import KIND_WALL, SceneBuilder
from monoloc.sim.shapes import add_wall
from monoloc.sim.textures import TextureBank, TextureLayers, TextureSpec

K = CameraIntrinsics(fx=200.0, fy=200.0, cx=79.5, cy=59.5, width_px=160, height_px=120)


def _halves(spec, rng):
    """Test texture: left half white, right half black (as seen from the front)."""
    img = np.zeros((spec.height_px, spec.width_px), np.uint8)
    img[:, : spec.width_px // 2] = 255
    return TextureLayers(albedo=img)


@pytest.fixture
def halves_texture():
    return TextureSpec("test_halves", 100, 50, seed=0)


def _wall_scene(spec, x_m=10.0, tilt_m=0.0):
    b = SceneBuilder()
    # Wall across the camera's view at x = x_m (tilted if tilt_m), facing the camera
    # (front on the left of a -> b).
    add_wall(b, (x_m + tilt_m, -5.0), (x_m - tilt_m, 5.0), -2.0, 3.0, spec, 10.0, KIND_WALL)
    return b.build()


def test_depth_is_exact_on_a_tilted_wall(halves_texture):
    scene = _wall_scene(halves_texture, x_m=10.0, tilt_m=2.0)
    T = T_world_from_cam_planar(0.0, 0.0, 0.0, 1.0)
    raster = rasterize(scene, None, T, K)
    depth = raster.depth_m
    assert np.isfinite(depth).mean() > 0.7  # the top rows see sky
    # Analytic ray / plane intersection at every pixel centre.
    u, v = np.meshgrid(np.arange(K.width_px), np.arange(K.height_px))
    rays_cam = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, float)], -1)
    rays = rays_cam @ T[:3, :3].T
    a, b = np.array([8.0, 5.0, 0.0]), np.array([12.0, -5.0, 0.0])
    normal = np.cross(b - a, [0, 0, 1.0])
    t = ((a - T[:3, 3]) @ normal) / (rays @ normal)
    hit = np.isfinite(depth)
    assert np.allclose(depth[hit], t[hit], rtol=1e-4)


def test_texture_is_not_mirrored_and_nearer_quad_occludes(halves_texture):
    scene = _wall_scene(halves_texture)
    T = T_world_from_cam_planar(0.0, 0.0, 0.0, 1.0)
    image = rasterize(scene, TextureBank({"test_halves": _halves}), T, K).albedo
    # The wall's texture column 0 is its left end seen from the front (y = +5, image left).
    assert image[60, 20] > 200 and image[60, 140] < 50
    b = SceneBuilder()
    add_wall(b, (10.0, -5.0), (10.0, 5.0), -2.0, 3.0, halves_texture, 10.0, KIND_WALL)
    add_wall(b, (5.0, -0.5), (5.0, 0.5), 0.5, 1.5, halves_texture, 10.0, KIND_WALL)
    raster = rasterize(b.build(), None, T, K)
    assert raster.depth_m[60, 80] == pytest.approx(5.0, rel=1e-4)
    assert raster.depth_m[60, 10] == pytest.approx(10.0, rel=1e-4)


def test_back_faces_are_culled(halves_texture):
    scene = _wall_scene(halves_texture)
    T = T_world_from_cam_planar(20.0, 0.0, np.pi, 1.0)  # behind the wall, looking back
    assert np.isinf(rasterize(scene, None, T, K).depth_m).all()

import hashlib

import numpy as np

from monoloc.core.camera import KITTI_CAM0
from monoloc.core.formats import kitti
from monoloc.core.formats.vehicle import read_vehicle
from monoloc.core.geometry import invert_rigid
from monoloc.sim import kitti_writer as kw
from monoloc.sim.generate import GenerateConfig, generate_dataset


def _project(points_cam: np.ndarray, P0: np.ndarray):
    uvw = points_cam @ P0[:, :3].T + P0[:, 3]
    return uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2], points_cam[:, 2]


def _interp_depth(depth: np.ndarray, u: np.ndarray, v: np.ndarray):
    """Depth at sub-pixel (u, v) by bilinear interpolation of inverse depth (exact inside
    one planar surface), and whether the 2x2 neighbourhood is one smooth surface."""
    h, w = depth.shape
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    ok = (u0 >= 0) & (v0 >= 0) & (u0 < w - 1) & (v0 < h - 1)
    u0, v0, a, b = u0[ok], v0[ok], (u - np.floor(u))[ok], (v - np.floor(v))[ok]
    quad = np.stack(
        [depth[v0, u0], depth[v0, u0 + 1], depth[v0 + 1, u0], depth[v0 + 1, u0 + 1]], axis=1
    )
    smooth = np.all(np.isfinite(quad), axis=1)
    smooth &= (quad.max(axis=1) - quad.min(axis=1)) < 0.03 * quad.min(axis=1) + 0.05
    inv = 1.0 / quad
    inv_i = (
        inv[:, 0] * (1 - a) * (1 - b)
        + inv[:, 1] * a * (1 - b)
        + inv[:, 2] * (1 - a) * b
        + inv[:, 3] * a * b
    )
    return ok, 1.0 / inv_i, smooth


def test_files_follow_the_kitti_layout(exact_dataset, tiny_config):
    root, info = exact_dataset
    assert [s["run"] for s in info["sequences"]] == ["map", "query"]
    assert "first frame of the map run" in info["world_frame"]
    for seq in info["sequences"]:
        d = kitti.sequence_dir(root, seq["id"])
        n = seq["frames"]
        # the query stops where the map run's stretch ends (monoloc.sim.urban.runs)
        assert n == 4 if seq["run"] == "map" else 1 <= n <= 4
        assert len(list((d / "image_0").glob("*.png"))) == n
        assert len(list((d / "velodyne").glob("*.bin"))) == n
        lines = (d / "calib.txt").read_text().splitlines()
        assert [ln.split(":")[0] for ln in lines] == ["P0", "P1", "P2", "P3", "Tr"]
        assert all(len(ln.split()) == 13 for ln in lines)
        assert np.loadtxt(d / "times.txt").shape == (n,)
        assert len(read_vehicle(d / "vehicle.txt")) == n
        assert kitti.read_poses(root / "poses" / f"{seq['id']}.txt").shape == (n, 4, 4)
        import cv2

        image = cv2.imread(str(d / "image_0" / "000000.png"), cv2.IMREAD_UNCHANGED)
        k = KITTI_CAM0.scaled(tiny_config.image_scale)
        assert image.dtype == np.uint8 and image.shape == (k.height_px, k.width_px)
    assert np.allclose(kitti.read_poses(root / "poses" / "00.txt")[0], np.eye(4), atol=1e-8)


def test_lidar_agrees_with_rendered_depth(exact_dataset):
    """Rule: project each LiDAR point with calib.txt (Tr, P0); where the 2x2 pixel
    neighbourhood is one smooth surface (not an edge, where LiDAR and camera may see
    different things from their 27 cm apart viewpoints), the depth must agree within
    5 cm for at least 95 % of points (the LiDAR has 2 cm range noise)."""
    root, info = exact_dataset
    d = kitti.sequence_dir(root, "00")
    calib = kitti.read_calib(d / "calib.txt")
    Tr, P0 = calib.T_cam0_from_lidar, calib.P_image_from_cam0[0]
    checked, agree = 0, 0
    for k in range(4):
        pts = kitti.read_scan(d / "velodyne" / f"{k:06d}.bin")[:, :3].astype(np.float64)
        cam = pts @ Tr[:3, :3].T + Tr[:3, 3]
        cam = cam[cam[:, 2] > 1.0]
        u, v, z = _project(cam, P0)
        depth = kw.read_depth(d / "depth" / f"{k:06d}.png")
        ok, z_img, smooth = _interp_depth(depth, u, v)
        err = np.abs(z_img - z[ok])[smooth]
        checked += len(err)
        agree += int(np.sum(err < 0.05))
    assert checked > 2000
    assert agree / checked > 0.95


def test_written_poses_reproduce_the_rendered_views(exact_dataset):
    """Back-project pixels of frame 0 with its written pose and depth, re-project them
    into frame 3 with its written pose: where visible (not occluded), the depth rendered
    in frame 3 is the predicted one."""
    root, _ = exact_dataset
    d = kitti.sequence_dir(root, "00")
    P0 = kitti.read_calib(d / "calib.txt").P_image_from_cam0[0]
    K = P0[:, :3]
    poses = kitti.read_poses(root / "poses" / "00.txt")
    d0, d3 = (kw.read_depth(d / "depth" / f"{k:06d}.png") for k in (0, 3))
    v, u = np.mgrid[0 : d0.shape[0] : 3, 0 : d0.shape[1] : 3]
    z = d0[v, u]
    keep = np.isfinite(z) & (z < 60)
    rays = np.stack([u[keep], v[keep], np.ones(keep.sum())], 1) @ np.linalg.inv(K).T
    pts_world = (rays * z[keep][:, None]) @ poses[0][:3, :3].T + poses[0][:3, 3]
    T_3_from_w = invert_rigid(poses[3])
    pts3 = pts_world @ T_3_from_w[:3, :3].T + T_3_from_w[:3, 3]
    pts3 = pts3[pts3[:, 2] > 1.0]
    u3, v3, z3 = _project(pts3, P0)
    ok, z_img, smooth = _interp_depth(d3, u3, v3)
    err = np.abs(z_img - z3[ok])[smooth]
    assert len(err) > 1000
    # A pose error of a few cm would move most points by more than 2 cm.
    assert np.mean(err < 0.02 + 0.002 * z3[ok][smooth]) > 0.9


def test_same_seed_gives_same_bytes(tmp_path, tiny_config):
    config = GenerateConfig(
        seed=5, runs=("map",), max_frames=2, image_scale=0.2, lidar=tiny_config.lidar
    )

    def digest(root):
        h = hashlib.sha256()
        for p in sorted(root.rglob("*")):
            if p.is_file():
                h.update(p.relative_to(root).as_posix().encode())
                h.update(p.read_bytes())
        return h.hexdigest()

    generate_dataset(config, tmp_path / "a")
    generate_dataset(config, tmp_path / "b")
    generate_dataset(GenerateConfig(**{**config.__dict__, "seed": 6}), tmp_path / "c")
    assert digest(tmp_path / "a") == digest(tmp_path / "b")
    assert digest(tmp_path / "a") != digest(tmp_path / "c")


def test_true_poses_are_the_written_ones_without_recording_errors(exact_dataset, tiny_config):
    from monoloc.core.geometry import planar_from_T_world_from_cam
    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.sim.urban.truth import true_planar_poses

    root, meta = exact_dataset
    truth = true_planar_poses(tiny_config, np.array(meta["T_simworld_from_zupworld"]))
    assert set(truth) == {"map", "query"}
    for seq in meta["sequences"]:
        written = read_kitti_sequence(root, seq["id"])
        poses = np.array([planar_from_T_world_from_cam(f.T_world_from_cam) for f in written.frames])
        assert truth[seq["run"]].shape == poses.shape
        np.testing.assert_allclose(truth[seq["run"]][:, :2], poses[:, :2], atol=1e-6)
        np.testing.assert_allclose(truth[seq["run"]][:, 2], poses[:, 2], atol=1e-8)

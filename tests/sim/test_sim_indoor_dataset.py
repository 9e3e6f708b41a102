"""The indoor dataset on disk: TUM files, depth encoding and noise, poses, determinism."""

import hashlib
import json

import numpy as np
import pytest

from monoloc.core.formats import tum
from monoloc.core.formats.vehicle import read_vehicle
from monoloc.core.geometry import invert_rigid
from monoloc.sim import tum_writer as tw
from monoloc.sim.generate import GenerateConfig, generate_dataset
from monoloc.sim.indoor import generate as indoor_generate
from monoloc.sim.indoor.generate import (
    indoor_config_for,
    render_rgbd,
    run_camera_config,
    run_scene,
)
from monoloc.sim.indoor.plan import T_world_from_cam_at, plan_indoor_runs
from monoloc.sim.indoor.sensors import misregister
from monoloc.sim.indoor.world import build_world
from monoloc.sim.recording import RecordingErrors

SEED = 4
EXACT = GenerateConfig(
    scenario="indoor",
    seed=SEED,
    runs=("map", "query"),
    max_frames=4,
    image_scale=0.5,
    errors=RecordingErrors.none(),
)
NOISY = GenerateConfig(**{**EXACT.__dict__, "errors": RecordingErrors(), "runs": ("map",)})


@pytest.fixture(scope="module")
def exact_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("indoor_exact")
    generate_dataset(EXACT, root)
    return root, json.loads((root / "dataset.json").read_text())


@pytest.fixture(scope="module")
def noisy_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("indoor_noisy")
    generate_dataset(NOISY, root)
    return root, json.loads((root / "dataset.json").read_text())


def _plan(config, run):
    indoor = indoor_config_for(config)
    world = build_world(indoor.rooms(), config.seed)
    return indoor, plan_indoor_runs(world, indoor, (run,), config.seed, config.max_frames)[0]


def test_runs_follow_the_tum_layout(noisy_dataset):
    root, info = noisy_dataset
    assert info["format"] == "tum-rgbd" and info["scenario"] == "indoor"
    assert "z-up" in info["world_frame"] and info["depth_scale_per_m"] == 5000
    run = root / "map"
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        head = (run / name).read_text().splitlines()[:3]
        assert all(line.startswith("#") for line in head), name
    rgb_t, rgb_files = tum.read_file_list(run / "rgb.txt")
    depth_t, depth_files = tum.read_file_list(run / "depth.txt")
    gt = tum.read_trajectory(run / "groundtruth.txt")
    gt_t, T = gt.timestamps_s, gt.T_world_from_cam
    signals = read_vehicle(run / "vehicle.txt")
    n = info["sequences"][0]["frames"]
    assert len(rgb_t) == len(depth_t) == len(signals) == n == 4
    assert all((run / f).is_file() for f in rgb_files + depth_files)
    assert rgb_files[0] == f"rgb/{tum.stamp_text(rgb_t[0])}.png"
    for stamps in (rgb_t, depth_t, gt_t):
        assert np.all(np.diff(stamps) > 0)
    # Depth is stamped a few ms off the colour image, within TUM's association tolerance.
    offset = depth_t - rgb_t
    assert np.all(np.abs(offset) < 0.02) and np.abs(offset).max() > 1e-4
    assert gt_t[0] <= min(rgb_t[0], depth_t[0]) and gt_t[-1] >= max(rgb_t[-1], depth_t[-1])
    assert np.all(np.diff(gt_t) < 0.006)  # 200 Hz motion capture
    assert np.allclose(signals.timestamps_s, rgb_t, atol=1e-6)
    assert np.allclose(np.linalg.det(T[:, :3, :3]), 1.0)
    camera = json.loads((run / "camera.json").read_text())
    assert camera["depth_scale_per_m"] == 5000 and camera["world_frame"] == "z-up"
    assert (camera["width"], camera["height"]) == (320, 240)
    assert camera["fx"] == pytest.approx(307.5)
    import cv2

    rgb = cv2.imread(str(run / rgb_files[0]), cv2.IMREAD_UNCHANGED)
    assert rgb.shape == (240, 320, 3) and rgb.dtype == np.uint8
    assert np.array_equal(rgb[:, :, 0], rgb[:, :, 2])
    depth = cv2.imread(str(run / depth_files[0]), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16 and depth.shape == (240, 320)


def test_depth_png_is_the_rendered_depth_up_to_quantisation(exact_dataset):
    root, _ = exact_dataset
    indoor, plan = _plan(EXACT, "map")
    scene, bank = run_scene(EXACT, indoor, plan)
    _, depth_files = tum.read_file_list(root / "map" / "depth.txt")
    for k in (0, 3):
        T = T_world_from_cam_at(plan, indoor.rig, plan.depth_times_s[k : k + 1])[0]
        _, true_m, _ = render_rgbd(
            scene,
            bank,
            T,
            T,
            indoor.intrinsics,
            plan.lighting,
            run_camera_config(indoor, plan),
            indoor.errors,
            indoor.render,
            np.random.default_rng(0),
        )
        written = tw.read_depth(root / "map" / depth_files[k])
        assert np.isfinite(true_m).all()  # a closed room: every pixel hits something
        encodable = true_m < 13.1
        assert np.abs(written - true_m)[encodable].max() <= 0.5 / 5000 + 1e-6
        assert np.all(written[~encodable] == 0)


def test_depth_noise_grows_with_depth_squared(noisy_dataset):
    """D435-like noise: the written depth differs from the rendered one by about
    sigma(z) = z^2 * disparity_std / (f * b); some pixels have no depth."""
    root, _ = noisy_dataset
    indoor, plan = _plan(NOISY, "map")
    scene, bank = run_scene(NOISY, indoor, plan)
    _, depth_files = tum.read_file_list(root / "map" / "depth.txt")
    T = T_world_from_cam_at(plan, indoor.rig, plan.depth_times_s[:1])[0]
    _, true_m, _ = render_rgbd(
        scene,
        bank,
        T,
        T,
        indoor.intrinsics,
        plan.lighting,
        run_camera_config(indoor, plan),
        indoor.errors,
        indoor.render,
        np.random.default_rng(0),
    )
    written = tw.read_depth(root / "map" / depth_files[0])
    valid = written > 0
    assert 0.001 < 1.0 - valid.mean() < 0.3
    # The written depth is registered with the extrinsic's residual: compare it with the
    # rendered depth moved the same way.
    registered = misregister(
        np.where(np.isfinite(true_m), true_m, 0.0).astype(np.float32), indoor.errors.depth
    )
    valid &= registered > 0
    z = registered[valid]
    normalised = (written[valid] - z) / indoor.errors.depth.sigma_m(z)
    assert 0.7 < np.std(normalised) < 1.3
    assert np.mean(np.abs(normalised) < 5) > 0.995
    near, far = z < 1.5, z > 3.0
    assert near.sum() > 500 and far.sum() > 500
    err = np.abs(written[valid] - z)
    assert np.median(err[far]) > 4 * np.median(err[near])


def _interp_depth(depth, u, v):
    """Depth at sub-pixel (u, v) from the 2x2 neighbours' inverse depth, and whether they
    form one smooth surface (no edge, all valid)."""
    h, w = depth.shape
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    ok = (u0 >= 0) & (v0 >= 0) & (u0 < w - 1) & (v0 < h - 1)
    u0, v0, a, b = u0[ok], v0[ok], (u - np.floor(u))[ok], (v - np.floor(v))[ok]
    quad = np.stack(
        [depth[v0, u0], depth[v0, u0 + 1], depth[v0 + 1, u0], depth[v0 + 1, u0 + 1]], axis=1
    )
    smooth = np.all(quad > 0, axis=1)
    smooth &= (quad.max(axis=1) - quad.min(axis=1)) < 0.02 * quad.min(axis=1) + 0.01
    inv = 1.0 / np.where(quad > 0, quad, 1.0)
    inv_i = (
        inv[:, 0] * (1 - a) * (1 - b)
        + inv[:, 1] * a * (1 - b)
        + inv[:, 2] * (1 - a) * b
        + inv[:, 3] * a * b
    )
    return ok, 1.0 / inv_i, smooth


def test_written_poses_reproduce_the_views(exact_dataset):
    """Back-project frame 0's depth with the ground truth at its stamp (interpolated from
    groundtruth.txt), re-project into frame 3: where visible, frame 3's depth agrees."""
    root, _ = exact_dataset
    run = root / "query"
    camera = json.loads((run / "camera.json").read_text())
    K = np.array([[camera["fx"], 0, camera["cx"]], [0, camera["fy"], camera["cy"]], [0, 0, 1]])
    gt = tum.read_trajectory(run / "groundtruth.txt")
    gt_t, T_gt = gt.timestamps_s, gt.T_world_from_cam
    stamps, files = tum.read_file_list(run / "depth.txt")
    d0, d3 = (tw.read_depth(run / files[k]) for k in (0, 3))
    T0, T3 = (tw.pose_at(gt_t, T_gt, stamps[k]) for k in (0, 3))
    assert np.linalg.norm(T3[:3, 3] - T0[:3, 3]) > 0.1  # the car moved
    v, u = np.mgrid[0 : d0.shape[0] : 2, 0 : d0.shape[1] : 2]
    z = d0[v, u]
    keep = z > 0
    rays = np.stack([u[keep], v[keep], np.ones(keep.sum())], 1) @ np.linalg.inv(K).T
    points_world = (rays * z[keep][:, None]) @ T0[:3, :3].T + T0[:3, 3]
    T_3_from_w = invert_rigid(T3)
    points_3 = points_world @ T_3_from_w[:3, :3].T + T_3_from_w[:3, 3]
    points_3 = points_3[points_3[:, 2] > 0.2]
    uvw = points_3 @ K.T
    ok, z_img, smooth = _interp_depth(d3, uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2])
    z3 = points_3[ok, 2][smooth]
    err = np.abs(z_img[smooth] - z3)
    assert len(err) > 5000
    # Exact poses give ~0.99; 1 cm or 0.1 deg of pose error gives < 0.9.
    assert np.mean(err < 0.002 + 0.001 * z3) > 0.97


def _digest(root):
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file():
            h.update(p.relative_to(root).as_posix().encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def test_same_seed_gives_same_bytes(tmp_path):
    config = GenerateConfig(
        scenario="indoor", seed=SEED, runs=("map", "train"), max_frames=2, image_scale=0.2
    )
    generate_dataset(config, tmp_path / "a")
    indoor_generate._STATE.clear()  # a fresh worker: nothing cached
    generate_dataset(config, tmp_path / "b")
    generate_dataset(GenerateConfig(**{**config.__dict__, "seed": SEED + 1}), tmp_path / "c")
    assert _digest(tmp_path / "a") == _digest(tmp_path / "b")
    assert _digest(tmp_path / "a") != _digest(tmp_path / "c")


def test_cli_generates_and_previews(tmp_path):
    from typer.testing import CliRunner

    from monoloc.sim.cli import app

    runner = CliRunner()
    out = tmp_path / "ds"
    args = ["generate", "--scenario", "indoor", "--seed", str(SEED), "--out", str(out)]
    result = runner.invoke(app, [*args, "--runs", "map", "--frames", "2", "--scale", "0.25"])
    assert result.exit_code == 0, result.output
    assert len(tum.read_file_list(out / "map" / "rgb.txt")[0]) == 2
    result = runner.invoke(app, ["preview", str(out)])
    assert result.exit_code == 0, result.output
    import cv2

    assert cv2.imread(str(out / "preview.png")) is not None
    bad = runner.invoke(app, [*args, "--runs", "map,night", "--frames", "1"])
    assert bad.exit_code != 0


def test_server_tum_reader_reads_the_output(noisy_dataset):
    """The contract: monoloc's own TUM reader associates every frame and gets the
    camera and the ground truth."""
    from monoloc.server.ingest.sources import read_tum_run

    root, info = noisy_dataset
    run = read_tum_run(root / "map")
    assert run.n_frames == info["sequences"][0]["frames"] and not run.read_skips
    assert run.intrinsics.fx == pytest.approx(307.5) and run.depth_scale_per_m == 5000
    gt = tum.read_trajectory(root / "map" / "groundtruth.txt")
    gt_t, T_gt = gt.timestamps_s, gt.T_world_from_cam
    frame = run.frames[-1]
    assert np.allclose(frame.T_world_from_cam, tw.pose_at(gt_t, T_gt, frame.timestamp_s), atol=1e-5)


def test_indoor_rejects_outdoor_only_runs_and_sizes(tmp_path):
    from monoloc.core.errors import InvalidInputError

    with pytest.raises(InvalidInputError, match="indoor runs"):
        generate_dataset(GenerateConfig(scenario="indoor", runs=("map", "night")), tmp_path)
    with pytest.raises(InvalidInputError, match="unknown size"):
        generate_dataset(GenerateConfig(scenario="indoor", size="huge"), tmp_path)

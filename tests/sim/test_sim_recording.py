"""The recording errors of the urban sim: each present with its stated size (measured from
generated data against the true values), deterministic in the seed, off in
``RecordingErrors.none()``; and the scene's hard cases: recurring buildings, night frames
lit by the road."""

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from monoloc.core.formats import kitti
from monoloc.sim import kitti_writer as kw
from monoloc.sim.camera import Lighting, render, shade
from monoloc.sim.generate import GenerateConfig, generate_dataset
from monoloc.sim.lidar import LidarConfig
from monoloc.sim.recording import RecordingErrors, material_gains
from monoloc.sim.render import rasterize
from monoloc.sim.scene import KIND_ROAD, KIND_WALL, concat_scenes
from monoloc.sim.textures import TextureBank
from monoloc.sim.urban.city import CityConfig, build_city, parked_cars
from monoloc.sim.urban.record import prepare_run_files, run_draws
from monoloc.sim.urban.runs import plan_runs, true_camera_poses
from monoloc.sim.urban.textures import URBAN_TEXTURES

RUNS = ("map", "query", "train", "night", "offcenter")


@pytest.fixture(scope="module")
def city_and_plans():
    config = GenerateConfig(seed=5, runs=RUNS)
    city = build_city(config.city_config(), config.seed)
    return config, city, plan_runs(city, config)


def _pose_errors(plan, config, errors, out_dir):
    """(n, 3) horizontal x, y and yaw error of the written poses against the true ones,
    and (n, 2) roll / pitch error (rad) from the rotation error's horizontal axis."""
    T_true = true_camera_poses(plan, config.rig)
    written = prepare_run_files(plan, replace(config, errors=errors), out_dir).T_written
    dxy = written[:, :2, 3] - T_true[:, :2, 3]
    R_err = written[:, :3, :3] @ np.transpose(T_true[:, :3, :3], (0, 2, 1))
    yaw = np.arctan2(R_err[:, 1, 0], R_err[:, 0, 0])
    tilt = np.stack([R_err[:, 2, 1], -R_err[:, 2, 0]], axis=1)  # small angles
    return np.column_stack([dxy, yaw]), tilt


def _autocorrelation(x: np.ndarray, lag: int) -> float:
    x = x - x.mean()
    return float(np.sum(x[:-lag] * x[lag:]) / np.sum(x * x))


def test_pose_errors_have_the_stated_size_and_vary_slowly(tmp_path, city_and_plans):
    config, _, plans = city_and_plans
    e = RecordingErrors()
    errs, tilts = zip(*(_pose_errors(p, config, e, tmp_path) for p in plans), strict=True)
    lag_1s = round(1.0 / (plans[0].frame_times_s[1] - plans[0].frame_times_s[0]))
    # Gauss-Markov with a 20 s time constant: correlation exp(-1/20) = 0.95 after 1 s
    # (white noise would give 0); per-run estimates are noisy over a few time constants.
    acf = [_autocorrelation(err[:, c], lag_1s) for err in errs for c in range(3)]
    assert np.median(acf) > 0.85 and min(acf) > 0.6
    every = np.concatenate(errs)
    horizontal_rms = math.sqrt(np.mean(every[:, 0] ** 2 + every[:, 1] ** 2))
    assert 0.6 * e.pose_error_m < horizontal_rms < 1.5 * e.pose_error_m
    yaw_rms = math.sqrt(np.mean(every[:, 2] ** 2))
    assert 0.6 * e.pose_yaw_error_rad < yaw_rms < 1.5 * e.pose_yaw_error_rad
    tilt_rms = math.sqrt(np.mean(np.concatenate(tilts) ** 2))
    assert 0.6 * e.pose_tilt_error_rad < tilt_rms < 1.5 * e.pose_tilt_error_rad
    # Each run draws its own error: map and query ground truths are not off alike.
    assert not np.allclose(errs[0][:50, :2], errs[1][:50, :2], atol=0.01)


def test_pose_errors_move_little_between_frames_like_an_ins(tmp_path, city_and_plans):
    """The written pose error is smooth at the frame rate: its rate (the error's change
    from one frame to the next over dt) stays within the RT3000's 0.05 km/h RMS velocity
    accuracy, while the first-order process alone (no smoothing) jumps 5 mm per frame."""
    config, _, plans = city_and_plans

    def rate_rms_mps(errors: RecordingErrors) -> float:
        rates = []
        for plan in plans:
            err, _ = _pose_errors(plan, config, errors, tmp_path)
            dt = np.diff(plan.frame_times_s)
            rates.append(np.hypot(*np.diff(err[:, :2], axis=0).T) / dt)
        return float(np.sqrt(np.mean(np.concatenate(rates) ** 2)))

    smooth = RecordingErrors()
    assert rate_rms_mps(smooth) < 0.05 / 3.6
    assert rate_rms_mps(replace(smooth, pose_error_smoothing_s=0.0)) > 0.03


def test_pose_and_calibration_errors_are_seeded_and_off_in_none(tmp_path, city_and_plans):
    config, _, plans = city_and_plans
    plan = plans[0]
    a = prepare_run_files(plan, config, tmp_path)
    b = prepare_run_files(plan, config, tmp_path)
    assert np.array_equal(a.T_written, b.T_written) and np.array_equal(a.Tr_written, b.Tr_written)
    assert not np.array_equal(a.T_written, prepare_run_files(plans[1], config, tmp_path).T_written)
    exact = prepare_run_files(plan, replace(config, errors=RecordingErrors.none()), tmp_path)
    assert np.allclose(exact.T_written, true_camera_poses(plan, config.rig), atol=1e-12)
    assert np.allclose(exact.Tr_written, config.rig.T_cam_from_lidar(), atol=1e-12)
    # The calibration written by each run is off by exactly the stated size.
    e = config.errors
    T_true = config.rig.T_cam_from_lidar()
    for p in plans:
        Tr = prepare_run_files(p, config, tmp_path).Tr_written
        shift = np.linalg.norm(Tr[:3, 3] - T_true[:3, 3])
        angle = math.acos(np.clip((np.trace(Tr[:3, :3] @ T_true[:3, :3].T) - 1) / 2, -1, 1))
        assert shift == pytest.approx(e.calib_translation_m, rel=1e-6)
        assert angle == pytest.approx(e.calib_rotation_rad, rel=1e-3)


def test_lidar_offsets_and_exposure_spread_have_the_stated_size(city_and_plans):
    """Over many runs: a run's sweep offset is uniform in +-lidar_sync_offset_s with white
    jitter of lidar_sync_jitter_s around it; exposure offsets have the stated spread."""
    _, _, plans = city_and_plans
    e = RecordingErrors()
    base = plans[0]
    runs = [run_draws(replace(base, seed=s), e) for s in range(400)]
    offsets = np.array([np.mean(r.lidar_time_offsets_s) for r in runs])
    assert np.all(np.abs(offsets) < e.lidar_sync_offset_s + 0.001)
    assert np.std(offsets) == pytest.approx(e.lidar_sync_offset_s / math.sqrt(3), rel=0.15)
    jitter = np.concatenate([r.lidar_time_offsets_s - r.lidar_time_offsets_s.mean() for r in runs])
    assert np.std(jitter) == pytest.approx(e.lidar_sync_jitter_s, rel=0.1)
    ev = np.array([r.exposure_bias_ev for r in runs])
    assert np.std(ev) == pytest.approx(e.exposure_bias_ev, rel=0.15)
    again = run_draws(base, e)
    assert np.array_equal(again.lidar_time_offsets_s, run_draws(base, e).lidar_time_offsets_s)
    off = run_draws(base, RecordingErrors.none())
    assert off.exposure_bias_ev == 0.0 and not np.any(off.lidar_time_offsets_s)
    assert material_gains(10, RecordingErrors.none(), np.random.default_rng(0)) is None


def _depth_misfit(points_lidar, T_cam_from_lidar, T_world_from_cam, P0, depth):
    """Mean |LiDAR depth - rendered depth| (m, each capped at 0.5) of the points off the
    ground (which hides a shift along the road) projected into the image."""
    cam = points_lidar @ T_cam_from_lidar[:3, :3].T + T_cam_from_lidar[:3, 3]
    world_z = cam @ T_world_from_cam[2, :3] + T_world_from_cam[2, 3]
    cam = cam[(cam[:, 2] > 2.0) & (cam[:, 2] < 40.0) & (world_z > 0.3)]
    uvw = cam @ P0[:, :3].T + P0[:, 3]
    u = np.round(uvw[:, 0] / uvw[:, 2]).astype(int)
    v = np.round(uvw[:, 1] / uvw[:, 2]).astype(int)
    h, w = depth.shape
    ok = (u >= 0) & (v >= 0) & (u < w) & (v < h)
    z_img = depth[v[ok], u[ok]]
    good = np.isfinite(z_img)
    assert good.sum() > 1000
    return float(np.mean(np.minimum(np.abs(z_img[good] - cam[ok][good][:, 2]), 0.5)))


def test_lidar_sweep_offset_shows_in_the_written_points(tmp_path):
    """Only the sync error on (no jitter, no motion distortion): the offset that best
    explains the written points against the exact rendered depth, searched over +-50 ms,
    is the run's drawn offset; assuming synchronised sensors fits worse."""
    errors = replace(RecordingErrors.none(), lidar_sync_offset_s=0.04)
    config = GenerateConfig(
        seed=11,
        runs=("map",),
        max_frames=3,
        image_scale=0.5,
        write_depth=True,
        errors=errors,
        lidar=LidarConfig(azimuth_steps=1000),
    )
    generate_dataset(config, tmp_path)
    info = json.loads((tmp_path / "dataset.json").read_text())
    drawn = info["sequences"][0]["lidar_time_offset_mean_s"]
    plan = plan_runs(build_city(config.city_config(), config.seed), config)[0]
    seq = kitti.sequence_dir(tmp_path, "00")
    P0 = kitti.read_calib(seq / "calib.txt").P_image_from_cam0[0]
    T_cam = true_camera_poses(plan, config.rig)
    T_v_lidar = config.rig.T_vehicle_from_lidar()
    grid = np.arange(-0.05, 0.0501, 0.0025)
    for k in range(3):
        points = kitti.read_scan(seq / "velodyne" / f"{k:06d}.bin")[:, :3].astype(np.float64)
        depth = kw.read_depth(seq / "depth" / f"{k:06d}.png")
        t = plan.frame_times_s[k]

        def misfit(dt, points=points, depth=depth, t=t, k=k):
            T_wl = plan.states.T_world_from_vehicle(np.array([t + dt]))[0] @ T_v_lidar
            return _depth_misfit(points, np.linalg.inv(T_cam[k]) @ T_wl, T_cam[k], P0, depth)

        fits = [misfit(dt) for dt in grid]
        best = grid[int(np.argmin(fits))]
        assert abs(best - drawn) <= 0.01  # the misfit is shallow: ground and side walls hide it
        if abs(drawn) > 0.02:
            assert misfit(0.0) > min(fits) + 0.004


def test_material_gains_change_each_texture_by_its_own_factor(city_and_plans):
    config, city, plans = city_and_plans
    scene = concat_scenes([city.static, parked_cars(city, 0)])
    bank = TextureBank(URBAN_TEXTURES)
    k = config.intrinsics().scaled(0.25)
    T = true_camera_poses(plans[0], config.rig)[40]
    raster = rasterize(scene, bank, T, k)
    day = Lighting.preset("day")
    gains = material_gains(len(scene.textures), RecordingErrors(), np.random.default_rng(1))
    assert np.std(np.log(gains)) == pytest.approx(RecordingErrors().material_gain, rel=0.2)
    plain = shade(raster, scene, T, k, day)
    tinted = shade(raster, scene, T, k, day, gains)
    hit = (raster.quad_id >= 0) & (plain > 1e-3)
    expected = gains[scene.quads.texture[raster.quad_id[hit]]]
    assert np.allclose(tinted[hit] / plain[hit], expected, rtol=1e-4)
    assert len(np.unique(np.round(expected, 4))) > 5


def test_districts_repeat_building_designs():
    """Street facades that recur at two or more places: a good share of the frontage with
    the default city, none when repetition is off."""

    def repeated_share(config: CityConfig) -> float:
        city = build_city(config, 2)
        q = city.static.quads
        front = [
            i
            for i, t in enumerate(city.static.textures)
            if t.kind == "facade"
            and t.param("ppm") == config.facade_texels_per_m
            and t.param("style") != "plain"
        ]
        walls = np.flatnonzero(np.isin(q.texture, front) & (q.kind == KIND_WALL))
        width_by_texture: dict[int, float] = {}
        places: dict[int, list[np.ndarray]] = {}
        for i in walls:
            tex = int(q.texture[i])
            width_by_texture[tex] = width_by_texture.get(tex, 0.0) + float(q.size_u[i])
            # Pieces of one wall start where the previous one ends; copies start apart.
            along_m = q.tex_offset_px[i, 0] / config.facade_texels_per_m
            start = q.origin[i, :2] - q.axis_u[i, :2] * along_m
            if all(np.linalg.norm(start - p) > 1.0 for p in places.setdefault(tex, [])):
                places[tex].append(start)
        total = sum(width_by_texture.values())
        repeated = sum(w for t, w in width_by_texture.items() if len(places[t]) >= 2)
        return repeated / total

    default = CityConfig.preset("small")
    share = repeated_share(default)
    assert share > 0.5 * default.repeated_building_fraction
    assert repeated_share(replace(default, repeated_building_fraction=0.0)) == 0.0


def test_night_frames_are_dominated_by_the_lit_road(city_and_plans):
    """At night the carriageway (lamps, low beams) is brighter than the facades, which
    are near black; by day the facades are the brighter ones."""
    config, city, plans = city_and_plans
    night = next(p for p in plans if p.kind == "night")
    scene = concat_scenes([city.static, parked_cars(city, night.car_variant)])
    bank = TextureBank(URBAN_TEXTURES)
    k = config.intrinsics().scaled(0.5)
    T_cams = true_camera_poses(night, config.rig)
    day = Lighting.preset("day", np.random.default_rng(0))
    ratios = {"night": [], "day": []}
    walls = {"night": [], "day": []}
    for idx in np.linspace(20, len(T_cams) - 20, 5).astype(int):
        for name, lighting in (("night", night.lighting), ("day", day)):
            raster = rasterize(scene, bank, T_cams[idx], k, night=lighting.night)
            kinds = scene.quads.kind[np.maximum(raster.quad_id, 0)]
            kinds[raster.quad_id < 0] = -1
            image = render(
                scene, bank, T_cams[idx], k, lighting, np.random.default_rng(idx), config.camera
            ).image.astype(float)
            road, wall = image[kinds == KIND_ROAD].mean(), image[kinds == KIND_WALL].mean()
            ratios[name].append(road / wall)
            walls[name].append(wall)
    assert np.median(ratios["night"]) > 1.5 and min(ratios["night"]) > 1.0
    assert max(ratios["day"]) < np.median(ratios["night"])
    # Facades dark at night (apart from lit windows and walls in the low beams), though
    # the exposure is at its limit.
    wall_ratio = np.array(walls["night"]) / np.array(walls["day"])
    assert np.median(wall_ratio) < 0.5 and wall_ratio.max() < 0.75


def test_error_groups_hold_every_error_once_and_only_turns_on_those():
    from dataclasses import fields

    from monoloc.core.errors import InvalidInputError
    from monoloc.sim.recording import ERROR_GROUPS

    grouped = [name for names in ERROR_GROUPS.values() for name in names]
    shape = {"pose_error_time_s", "pose_error_smoothing_s"}
    assert sorted(grouped) == sorted(f.name for f in fields(RecordingErrors) if f.name not in shape)
    assert RecordingErrors.only(*ERROR_GROUPS) == RecordingErrors()
    assert RecordingErrors.only() == RecordingErrors.none()
    calibration = RecordingErrors.only("calibration")
    assert calibration.calib_rotation_rad == RecordingErrors().calib_rotation_rad > 0
    assert calibration.pose_error_m == 0 and not calibration.lidar_motion_distortion
    assert replace(calibration, calib_translation_m=0, calib_rotation_rad=0) == (
        RecordingErrors.none()
    )
    with pytest.raises(InvalidInputError, match="unknown recording error groups"):
        RecordingErrors.only("pose", "weather")


def test_frame_pose_error_is_white_of_its_size_and_leaves_the_rest_as_it_was(
    tmp_path, city_and_plans
):
    """``pose_frame_error_m`` adds a horizontal error drawn anew every frame (issue 47):
    neighbouring frames' errors uncorrelated, RMS as stated, heading and every other draw
    of the run unchanged (its own random stream)."""
    config, _, plans = city_and_plans
    plan = plans[0]
    base = RecordingErrors()
    white = replace(base, pose_frame_error_m=0.2)
    smooth_err, _ = _pose_errors(plan, config, base, tmp_path)
    white_err, _ = _pose_errors(plan, config, white, tmp_path)
    extra = white_err[:, :2] - smooth_err[:, :2]
    rms = math.sqrt(np.mean(np.sum(extra**2, axis=1)))
    assert 0.8 * 0.2 < rms < 1.2 * 0.2
    assert max(abs(_autocorrelation(extra[:, c], 1)) for c in range(2)) < 0.2
    np.testing.assert_array_equal(white_err[:, 2], smooth_err[:, 2])
    a = prepare_run_files(plan, replace(config, errors=base), tmp_path)
    b = prepare_run_files(plan, replace(config, errors=white), tmp_path)
    np.testing.assert_array_equal(a.Tr_written, b.Tr_written)
    np.testing.assert_array_equal(a.speed_mps, b.speed_mps)
    assert RecordingErrors().pose_frame_error_m == 0.0  # off by default


def test_stereo_disparity_offset_moves_what_sgbm_measures_by_the_offset():
    """``shift_right_image`` writes the right image so that the server's own stereo
    matcher measures every disparity larger by the offset (issue 47's stereo lead)."""
    from monoloc.server.vision.stereo import disparity_map
    from monoloc.sim.recording import shift_right_image

    rng = np.random.default_rng(11)
    import cv2

    texture = cv2.GaussianBlur(rng.integers(0, 256, (200, 400)).astype(np.uint8), (3, 3), 0)
    left, right = texture[:, 60:360], texture[:, 72:372]  # disparity 12 px everywhere
    fx_px, baseline_m = 718.0, 0.54

    def mean_disparity(r):
        d = disparity_map(left, r, fx_px, baseline_m)[20:-20, 80:-20]
        return float(np.mean(d[d > 0]))

    before = mean_disparity(right)
    assert abs(before - 12.0) < 0.02
    assert abs(mean_disparity(shift_right_image(right, 1.0)) - before - 1.0) < 0.02
    # SGBM's sub-pixel fit pulls fractions toward whole pixels (pixel locking): a
    # fractional offset shows at 0.5-1x its size, always its sign
    for offset_px in (0.3, -0.5):
        moved = mean_disparity(shift_right_image(right, offset_px)) - before
        assert 0.5 * abs(offset_px) < abs(moved) <= 1.05 * abs(offset_px)
        assert np.sign(moved) == np.sign(offset_px)
    assert shift_right_image(right, 0.0) is right


def test_stereo_disparity_offset_is_a_runs_own_draw_and_off_by_default(city_and_plans):
    from monoloc.sim.urban.record import run_draws

    _, _, plans = city_and_plans
    assert RecordingErrors().stereo_disparity_error_px == 0.0
    assert run_draws(plans[0], RecordingErrors()).stereo_disparity_offset_px == 0.0
    on = replace(RecordingErrors(), stereo_disparity_error_px=0.2)
    offsets = [run_draws(p, on).stereo_disparity_offset_px for p in plans]
    assert len(set(offsets)) == len(plans) and all(0 < abs(o) < 1.0 for o in offsets)
    a, b = run_draws(plans[0], RecordingErrors()), run_draws(plans[0], on)
    assert a.exposure_bias_ev == b.exposure_bias_ev
    np.testing.assert_array_equal(a.lidar_time_offsets_s, b.lidar_time_offsets_s)

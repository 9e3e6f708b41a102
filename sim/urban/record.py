"""Recording one urban run: the measured values its files carry, its metadata files, and
rendering a chunk of its frames (run in worker processes; each keeps its city and
texture cache)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.formats import kitti
from monoloc.core.geometry import invert_rigid
from monoloc.sim import kitti_writer as kw
from monoloc.sim.camera import CameraConfig, render
from monoloc.sim.lidar import firing_times_s, scan
from monoloc.sim.recording import (
    apply_pose_errors,
    exposure_bias_ev,
    lidar_time_offsets_s,
    material_gains,
    measured_signals,
    perturb_calibration,
    shift_right_image,
    stereo_disparity_offset_px,
)
from monoloc.sim.scene import concat_scenes
from monoloc.sim.textures import TextureBank
from monoloc.sim.urban.city import build_city, parked_cars
from monoloc.sim.urban.runs import T_vehicle_from_run_cam, true_camera_poses
from monoloc.sim.urban.textures import URBAN_TEXTURES


@dataclass(frozen=True)
class WrittenRun:
    """What a run's files carry: T_written (n, 4, 4) poses in the sim world (with the
    recording's pose errors), Tr_written (4, 4) calibration, measured signals (n,); and
    what its camera and LiDAR errors came out as (:class:`RunDraws`)."""

    T_written: np.ndarray
    Tr_written: np.ndarray
    speed_mps: np.ndarray
    yaw_rate_radps: np.ndarray
    draws: RunDraws


@dataclass(frozen=True)
class RunDraws:
    """A run's own draw of the camera and LiDAR errors: exposure offset (EV), each
    frame's LiDAR sweep centre minus its exposure time (n,) s, the stereo pair's disparity
    offset (px). Deterministic in the run's seed; the rendering workers and dataset.json
    get the same values."""

    exposure_bias_ev: float
    lidar_time_offsets_s: np.ndarray
    stereo_disparity_offset_px: float = 0.0


def run_draws(plan, errors) -> RunDraws:
    """The :class:`RunDraws` of ``plan`` under ``errors``."""
    n = len(plan.frame_times_s)
    return RunDraws(
        exposure_bias_ev(errors, np.random.default_rng([plan.seed, 2])),
        lidar_time_offsets_s(n, errors, np.random.default_rng([plan.seed, 4])),
        stereo_disparity_offset_px(errors, np.random.default_rng([plan.seed, 7])),
    )


def prepare_run_files(plan, config, out_dir: Path) -> WrittenRun:
    """Decide the measured values of a run (deterministic in its seed)."""
    rng = np.random.default_rng([plan.seed, 1])
    errors = config.errors
    T_true = true_camera_poses(plan, config.rig)
    T_written = apply_pose_errors(
        T_true, plan.frame_times_s, errors, rng, np.random.default_rng([plan.seed, 6])
    )
    T_cam_from_lidar = invert_rigid(T_vehicle_from_run_cam(plan, config.rig)) @ (
        config.rig.T_vehicle_from_lidar()
    )
    Tr_written = perturb_calibration(T_cam_from_lidar, errors, rng)
    st = plan.states.sample(plan.frame_times_s)
    speed, yaw_rate = measured_signals(st["speed_mps"], st["yaw_rate_radps"], errors, rng)
    return WrittenRun(T_written, Tr_written, speed, yaw_rate, run_draws(plan, errors))


def run_intrinsics(plan, config) -> CameraIntrinsics:
    """The camera that records ``plan``: the mapping camera, or the run's own (with its
    lens), at the config's image scale."""
    if plan.camera is None:
        return config.intrinsics()
    return plan.camera.intrinsics(config.image_scale)


def writes_stereo(plan, config) -> bool:
    """The stereo head is the mapping camera's: a fleet camera's run has no image_1/."""
    return config.write_stereo and plan.camera is None


def write_run_metadata(plan, written: WrittenRun, frames: dict, config, out_dir: Path) -> None:
    """calib.txt, times.txt, vehicle.txt and poses/NN.txt of one run; camera.json for a
    run whose camera is not the mapping camera."""
    seq = kitti.sequence_dir(out_dir, plan.seq_id)
    subs = ("image_0", "velodyne") + (("depth",) if config.write_depth else ())
    for sub in subs + (("image_1",) if writes_stereo(plan, config) else ()):
        (seq / sub).mkdir(parents=True, exist_ok=True)
    intrinsics = run_intrinsics(plan, config)
    kw.write_calib(
        seq / "calib.txt", intrinsics.K, written.Tr_written, config.rig.stereo_baseline_m
    )
    if plan.camera is not None:
        kw.write_camera_json(
            seq / "camera.json", intrinsics, T_vehicle_from_run_cam(plan, config.rig)
        )
    times = plan.frame_times_s - plan.frame_times_s[0]
    kw.write_times(seq / "times.txt", times)
    kw.write_vehicle(seq / "vehicle.txt", times, written.speed_mps, written.yaw_rate_radps)
    T_kitti_from_sim = invert_rigid(frames["T_simworld_from_kittiworld"])
    kw.write_poses(kitti.poses_path(out_dir, plan.seq_id), T_kitti_from_sim @ written.T_written)


_STATE: dict = {}


def _world(config, plan):
    """City, per-variant scene and texture bank of this process (built once)."""
    key = (config.seed, config.city_config())
    if _STATE.get("key") != key:
        _STATE.clear()
        _STATE["key"] = key
        _STATE["city"] = build_city(config.city_config(), config.seed)
        _STATE["bank"] = TextureBank(URBAN_TEXTURES, max_bytes=700_000_000)
        _STATE["scenes"] = {}
    city = _STATE["city"]
    if plan.car_variant not in _STATE["scenes"]:
        _STATE["scenes"][plan.car_variant] = concat_scenes(
            [city.static, parked_cars(city, plan.car_variant)]
        )
    return _STATE["scenes"][plan.car_variant], _STATE["bank"]


def render_chunk(config, plan, first: int, last: int, out_dir: Path) -> None:
    """Render and write frames [first, last) of ``plan``."""
    import cv2

    cv2.setNumThreads(1)
    scene, bank = _world(config, plan)
    seq = kitti.sequence_dir(out_dir, plan.seq_id)
    rig, errors = config.rig, config.errors
    intrinsics = run_intrinsics(plan, config)
    draws = run_draws(plan, errors)
    palette = errors
    if plan.material_gain is not None:
        palette = replace(errors, material_gain=plan.material_gain)
    gains = material_gains(len(scene.textures), palette, np.random.default_rng([plan.seed, 5]))
    cam_cfg = config.camera
    bias = draws.exposure_bias_ev + plan.exposure_offset_ev
    cam_cfg = CameraConfig(
        **{**cam_cfg.__dict__, "exposure_bias_ev": cam_cfg.exposure_bias_ev + bias}
    )
    if not errors.sensor_noise:
        cam_cfg = CameraConfig(**{**cam_cfg.__dict__, "shot_noise": 0.0, "read_noise": 0.0})
    T_v_cam, T_v_lidar = T_vehicle_from_run_cam(plan, rig), rig.T_vehicle_from_lidar()
    for k in range(first, last):
        t = float(plan.frame_times_s[k])
        rng = np.random.default_rng([plan.seed, 3, k])
        T_wv = plan.states.T_world_from_vehicle(np.array([t]))[0]
        frame = render(
            scene,
            bank,
            T_wv @ T_v_cam,
            intrinsics,
            plan.lighting,
            rng,
            cam_cfg,
            material_gain=gains,
        )
        kw.write_image(seq / "image_0" / f"{k:06d}.png", frame.image)
        if writes_stereo(plan, config):
            # Its own sensor noise (a stream of its own, so image_0 and the scan keep
            # their bytes), camera 0's exposure: a synchronised stereo head.
            right = render(
                scene,
                bank,
                T_wv @ rig.T_vehicle_from_cam1(),
                intrinsics,
                plan.lighting,
                np.random.default_rng([plan.seed, 4, k]),
                cam_cfg,
                exposure=frame.exposure,
                material_gain=gains,
            )
            right_image = shift_right_image(right.image, draws.stereo_disparity_offset_px)
            kw.write_image(seq / "image_1" / f"{k:06d}.png", right_image)
        if config.write_depth:
            kw.write_depth(seq / "depth" / f"{k:06d}.png", frame.depth_m)
        if config.write_lidar:
            t_sweep = t + float(draws.lidar_time_offsets_s[k])
            if errors.lidar_motion_distortion:
                T_wl = (
                    plan.states.T_world_from_vehicle(firing_times_s(t_sweep, config.lidar))
                    @ T_v_lidar
                )
            else:
                T_wl = plan.states.T_world_from_vehicle(np.array([t_sweep]))[0] @ T_v_lidar
            points = scan(scene, T_wl, config.lidar, rng, bank)
            kitti.write_scan(seq / "velodyne" / f"{k:06d}.bin", points)

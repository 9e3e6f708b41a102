"""Generate the indoor dataset: rooms with a race track, a 1:10 car with an RGB-D camera,
written in the TUM RGB-D layout (``monoloc.sim.tum_writer``), one folder per run.

World frame of every ``groundtruth.txt``: the motion-capture frame, z up, origin on the
floor at the centre of the main room (``monoloc.sim.indoor.room``); all runs share it. Generation is
deterministic in the seed: the same config gives the same bytes, whatever the number of
worker processes.
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import replace
from pathlib import Path

import numpy as np

from monoloc.core.formats import tum
from monoloc.sim import tum_writer as tw
from monoloc.sim.camera import CameraConfig, auto_exposure, expose, shade
from monoloc.sim.indoor.infield import obstacles_scene
from monoloc.sim.indoor.info import dataset_info
from monoloc.sim.indoor.plan import (
    IndoorConfig,
    IndoorRunPlan,
    T_world_from_cam_at,
    indoor_runs,
    plan_indoor_runs,
)
from monoloc.sim.indoor.sensors import IndoorErrors, mocap_noise, noisy_depth
from monoloc.sim.indoor.textures import INDOOR_TEXTURES
from monoloc.sim.indoor.world import build_world
from monoloc.sim.recording import RecordingErrors, measured_signals
from monoloc.sim.render import rasterize
from monoloc.sim.scene import concat_scenes
from monoloc.sim.summary import DatasetSummary, SequenceSummary
from monoloc.sim.textures import TextureBank

CHUNK_FRAMES = 25


def indoor_config_for(config) -> IndoorConfig:
    """The IndoorConfig of a ``monoloc.sim.generate.GenerateConfig``: its ``indoor`` field,
    else the size preset, with every error off when ``errors`` is ``RecordingErrors.none()``
    (the CLI's --no-errors); ``image_scale`` scales the camera."""
    indoor = config.indoor
    if indoor is None:
        exact = config.errors == RecordingErrors.none()
        indoor = IndoorConfig.preset(config.size, IndoorErrors.none() if exact else None)
    if config.image_scale != 1.0:
        indoor = replace(indoor, intrinsics=indoor.intrinsics.scaled(config.image_scale))
    return indoor


def render_rgbd(scene, bank, T_rgb, T_depth, intrinsics, lighting, camera, errors, render_cfg, rng):
    """One RGB-D frame: image (H, W) uint8 seen from ``T_rgb`` (T_world_from_cam), the
    exact depth (H, W) float32 (inf: nothing) seen from ``T_depth``, and the depth the
    sensor reports (float32 m, 0 = none)."""
    raster = rasterize(scene, bank, T_rgb, intrinsics, render_cfg, night=lighting.night)
    radiance = shade(raster, scene, T_rgb, intrinsics, lighting)
    image = expose(radiance, auto_exposure(radiance, camera), camera, rng)
    if np.array_equal(T_rgb, T_depth):
        depth = raster.depth_m
    else:
        depth = rasterize(scene, None, T_depth, intrinsics, render_cfg).depth_m
    return image, depth, noisy_depth(depth, image, errors.depth, rng)


def _source(config, plan: IndoorRunPlan) -> str:
    return f"monoloc sim indoor seed {config.seed} run {plan.run}"


def write_run_metadata(config, indoor: IndoorConfig, plan: IndoorRunPlan, out_dir: Path) -> None:
    """rgb.txt, depth.txt, groundtruth.txt, vehicle.txt and camera.json of one run."""
    run_dir = Path(out_dir) / plan.run
    for sub in ("rgb", "depth"):
        (run_dir / sub).mkdir(parents=True, exist_ok=True)
    rgb_stamps = plan.stamp0_s + plan.rgb_times_s
    depth_stamps = plan.stamp0_s + plan.depth_times_s
    source = _source(config, plan)
    tw.write_file_list(
        run_dir / "rgb.txt",
        "color images",
        source,
        rgb_stamps,
        [f"rgb/{tum.stamp_text(t)}.png" for t in rgb_stamps],
    )
    tw.write_file_list(
        run_dir / "depth.txt",
        "depth maps",
        source,
        depth_stamps,
        [f"depth/{tum.stamp_text(t)}.png" for t in depth_stamps],
    )
    rng = np.random.default_rng([plan.seed, 1])
    e = indoor.errors
    T_true = T_world_from_cam_at(plan, indoor.rig, plan.mocap_times_s)
    tw.write_ground_truth(
        run_dir / "groundtruth.txt",
        source,
        plan.stamp0_s + plan.mocap_times_s,
        mocap_noise(T_true, e, rng),
    )
    signal_errors = RecordingErrors(
        speed_scale_error=e.speed_scale_error,
        speed_bias_mps=e.speed_bias_mps,
        speed_noise_mps=e.speed_noise_mps,
        yaw_rate_bias_radps=e.yaw_rate_bias_radps,
        yaw_rate_noise_radps=e.yaw_rate_noise_radps,
    )
    st = plan.states.sample(plan.rgb_times_s)
    speed, yaw_rate = measured_signals(st["speed_mps"], st["yaw_rate_radps"], signal_errors, rng)
    tw.write_vehicle(run_dir / "vehicle.txt", rgb_stamps, speed, yaw_rate)
    tum.write_camera_json(
        run_dir / "camera.json",
        indoor.intrinsics,
        {
            "world_frame": "z-up",
            "depth_registered_to": "rgb",
            "T_vehicle_from_cam": [
                [float(v) for v in row] for row in indoor.rig.T_vehicle_from_cam()
            ],
        },
    )


_STATE: dict = {}


def run_scene(config, indoor: IndoorConfig, plan: IndoorRunPlan):
    """World, per-(room, obstacle variant) scene and texture bank of this process."""
    key = (config.seed, indoor.main_room, indoor.train_room)
    if _STATE.get("key") != key:
        _STATE.clear()
        _STATE.update(
            key=key,
            world=build_world(indoor.rooms(), config.seed),
            scenes={},
            bank=TextureBank(INDOOR_TEXTURES, max_bytes=600_000_000),
        )
    scene_key = (plan.room, plan.obstacles_variant)
    if scene_key not in _STATE["scenes"]:
        room = _STATE["world"].rooms[plan.room]
        obstacles = obstacles_scene(
            room.slots,
            config.seed * 1009 + (plan.room == "train"),
            plan.obstacles_variant,
            change_fraction=indoor.obstacle_change_fraction,
        )
        _STATE["scenes"][scene_key] = concat_scenes([room.static, obstacles])
    return _STATE["scenes"][scene_key], _STATE["bank"]


def run_camera_config(indoor: IndoorConfig, plan: IndoorRunPlan):
    """The run's camera settings: its exposure offset, noise on or off."""
    e = indoor.errors
    cam = indoor.camera
    bias = (
        float(np.random.default_rng([plan.seed, 2]).normal(0.0, e.exposure_bias_ev))
        if (e.exposure_bias_ev)
        else 0.0
    )
    cam = CameraConfig(**{**cam.__dict__, "exposure_bias_ev": cam.exposure_bias_ev + bias})
    if not e.sensor_noise:
        cam = CameraConfig(**{**cam.__dict__, "shot_noise": 0.0, "read_noise": 0.0})
    return cam


def render_chunk(
    config, indoor: IndoorConfig, plan: IndoorRunPlan, first: int, last: int, out_dir: Path
) -> None:
    """Render and write frames [first, last) of ``plan``."""
    import cv2

    cv2.setNumThreads(1)
    scene, bank = run_scene(config, indoor, plan)
    run_dir = Path(out_dir) / plan.run
    cam = run_camera_config(indoor, plan)
    T_rgb = T_world_from_cam_at(plan, indoor.rig, plan.rgb_times_s[first:last])
    T_depth = T_world_from_cam_at(plan, indoor.rig, plan.depth_times_s[first:last])
    for i, k in enumerate(range(first, last)):
        rng = np.random.default_rng([plan.seed, 3, k])
        image, _, depth = render_rgbd(
            scene,
            bank,
            T_rgb[i],
            T_depth[i],
            indoor.intrinsics,
            plan.lighting,
            cam,
            indoor.errors,
            indoor.render,
            rng,
        )
        rgb_stamp = tum.stamp_text(plan.stamp0_s + plan.rgb_times_s[k])
        depth_stamp = tum.stamp_text(plan.stamp0_s + plan.depth_times_s[k])
        tw.write_rgb(run_dir / "rgb" / f"{rgb_stamp}.png", image)
        tw.write_depth(run_dir / "depth" / f"{depth_stamp}.png", depth)


def generate_indoor_dataset(
    config, out_dir: Path, progress: Callable[[str, int, int], None] | None = None
) -> DatasetSummary:
    """Write the indoor dataset of a ``GenerateConfig`` under ``out_dir``; returns a
    ``monoloc.sim.summary.DatasetSummary``."""
    start = time.perf_counter()
    out_dir = Path(out_dir)
    indoor = indoor_config_for(config)
    world = build_world(indoor.rooms(), config.seed)
    runs = indoor_runs(config.runs)
    plans = plan_indoor_runs(world, indoor, runs, config.seed, config.max_frames)
    for plan in plans:
        write_run_metadata(config, indoor, plan, out_dir)
    jobs = [
        (plan, a, min(a + CHUNK_FRAMES, len(plan.rgb_times_s)))
        for plan in plans
        for a in range(0, len(plan.rgb_times_s), CHUNK_FRAMES)
    ]
    done = dict.fromkeys((p.run for p in plans), 0)

    def report(plan, a, b):
        done[plan.run] += b - a
        if progress is not None:
            progress(plan.run, done[plan.run], len(plan.rgb_times_s))

    if config.workers <= 1:
        for plan, a, b in jobs:
            render_chunk(config, indoor, plan, a, b, out_dir)
            report(plan, a, b)
    else:
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=config.workers, mp_context=ctx) as pool:
            futures = {
                pool.submit(render_chunk, config, indoor, plan, a, b, out_dir): (plan, a, b)
                for plan, a, b in jobs
            }
            for fut in as_completed(futures):
                fut.result()
                report(*futures[fut])
    tw.write_dataset_json(out_dir, dataset_info(config, indoor, world, plans))
    summaries = [
        SequenceSummary(p.run, p.run, p.lighting.name, len(p.rgb_times_s), p.route_length_m)
        for p in plans
    ]
    return DatasetSummary(root=out_dir, sequences=summaries, seconds=time.perf_counter() - start)

"""Speed and realism of the synthetic world, per core, at KITTI resolution.

Renders consecutive frames of the small city's map route (camera image + exact depth +
a motion-distorted 64-beam LiDAR sweep), single-threaded (cv2.setNumThreads(1)), after
one warm-up pass over the same frames (textures generated, LiDAR kernel compiled), and
prints frames/s next to the 5 fps target. Also counts ORB features (METHOD: 1000 max,
after a 5x5 Gaussian blur) per lighting against the 500-per-day-frame bar. Then the
indoor scenario: camera + D435-like depth at 640x480 (colour raster, a second depth-only
raster at the depth stream's own stamp, depth noise) along the small room's map lap,
timed the same way, and ORB features per frame (map lap and training room) against the
300 bar. Writes bench/results/sim.json (indoor figures under keys starting "indoor_").

    python -m bench.sim [--frames 40] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

TARGET_FPS = 5.0
ORB_TARGET = 500
INDOOR_ORB_TARGET = 300


def main() -> None:
    import cv2

    from monoloc.sim.camera import Lighting, render
    from monoloc.sim.generate import GenerateConfig
    from monoloc.sim.lidar import firing_times_s, scan
    from monoloc.sim.scene import concat_scenes
    from monoloc.sim.textures import TextureBank
    from monoloc.sim.urban.city import build_city, parked_cars
    from monoloc.sim.urban.runs import plan_runs
    from monoloc.sim.urban.textures import URBAN_TEXTURES

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    config = GenerateConfig(seed=args.seed, runs=("map",), max_frames=args.frames)
    t0 = time.perf_counter()
    city = build_city(config.city_config(), config.seed)
    plan = plan_runs(city, config)[0]
    scene = concat_scenes([city.static, parked_cars(city, 0)])
    build_s = time.perf_counter() - t0
    bank = TextureBank(URBAN_TEXTURES)
    rig = config.rig
    T_v_cam, T_v_lidar = rig.T_vehicle_from_cam(), rig.T_vehicle_from_lidar()
    intrinsics = config.intrinsics()
    orb = cv2.ORB_create(1000)

    def frame(k: int, lighting):
        t = float(plan.frame_times_s[k])
        rng = np.random.default_rng(k)
        T_wv = plan.states.T_world_from_vehicle(np.array([t]))[0]
        a = time.perf_counter()
        image = render(scene, bank, T_wv @ T_v_cam, intrinsics, lighting, rng).image
        b = time.perf_counter()
        T_wl = plan.states.T_world_from_vehicle(firing_times_s(t, config.lidar)) @ T_v_lidar
        points = scan(scene, T_wl, config.lidar, rng, bank)
        c = time.perf_counter()
        return image, points, b - a, c - b

    n = len(plan.frame_times_s)
    t0 = time.perf_counter()
    for k in range(n):
        frame(k, plan.lighting)
    warmup_s = time.perf_counter() - t0
    cam_s, lidar_s, n_points = [], [], []
    for k in range(n):
        _, points, tc, tl = frame(k, plan.lighting)
        cam_s.append(tc)
        lidar_s.append(tl)
        n_points.append(len(points))
    per_frame = float(np.mean(cam_s) + np.mean(lidar_s))
    fps = 1.0 / per_frame
    orb_counts = {}
    for name in ("day", "dusk", "night"):
        lighting = (
            Lighting.preset(name, np.random.default_rng(1)) if name != "day" else (plan.lighting)
        )
        counts = []
        for k in np.linspace(0, n - 1, 5).astype(int):
            image = frame(int(k), lighting)[0]
            counts.append(len(orb.detect(cv2.GaussianBlur(image, (5, 5), 0), None)))
        orb_counts[name] = float(np.mean(counts))
    rows = [
        ("frames/s per core (camera+depth+LiDAR)", f"{fps:.1f}", f">= {TARGET_FPS:.0f}"),
        ("  camera + depth ms/frame", f"{1000 * np.mean(cam_s):.1f}", ""),
        ("  LiDAR ms/frame", f"{1000 * np.mean(lidar_s):.1f}", ""),
        ("  LiDAR points/scan", f"{np.mean(n_points):.0f}", "KITTI ~120000"),
        ("first pass ms/frame (textures, JIT)", f"{1000 * warmup_s / n:.0f}", ""),
        ("city build s", f"{build_s:.2f}", ""),
    ] + [
        (f"ORB features/frame, {k}", f"{v:.0f}", f">= {ORB_TARGET}" if k == "day" else "")
        for k, v in orb_counts.items()
    ]
    indoor, indoor_rows = _indoor(args.frames, args.seed, 1000 * float(np.mean(cam_s)))
    rows += indoor_rows
    width = max(len(r[0]) for r in rows)
    print(f"{'measure':<{width}}  {'value':>9}  target/baseline")
    for name, value, target in rows:
        print(f"{name:<{width}}  {value:>9}  {target}")
    out = Path(__file__).parent / "results" / "sim.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps(
            {
                "frames": n,
                "seed": args.seed,
                "fps_per_core": fps,
                "target_fps": TARGET_FPS,
                "camera_ms": 1000 * float(np.mean(cam_s)),
                "lidar_ms": 1000 * float(np.mean(lidar_s)),
                "lidar_points": float(np.mean(n_points)),
                "warmup_ms_per_frame": 1000 * warmup_s / n,
                "city_build_s": build_s,
                "orb_per_frame": orb_counts,
                "orb_target_day": ORB_TARGET,
                **indoor,
            },
            indent=2,
        )
        + "\n"
    )
    print(f"wrote {out}")


def _indoor(
    n_frames: int, seed: int, outdoor_camera_ms: float
) -> tuple[dict, list[tuple[str, str, str]]]:
    """Indoor camera + depth speed (per core) and ORB features per frame; the outdoor
    camera + depth time of the same run is the baseline next to it."""
    import cv2

    from monoloc.sim.generate import GenerateConfig
    from monoloc.sim.indoor.generate import (
        indoor_config_for,
        render_rgbd,
        run_camera_config,
        run_scene,
    )
    from monoloc.sim.indoor.plan import T_world_from_cam_at, plan_indoor_runs
    from monoloc.sim.indoor.world import build_world

    config = GenerateConfig(scenario="indoor", seed=seed, runs=("map", "train"))
    indoor = indoor_config_for(config)
    t0 = time.perf_counter()
    world = build_world(indoor.rooms(), seed)
    build_s = time.perf_counter() - t0
    plans = plan_indoor_runs(world, indoor, config.runs, seed)
    orb = cv2.ORB_create(1000)

    def frames(plan, picks):
        scene, bank = run_scene(config, indoor, plan)
        cam = run_camera_config(indoor, plan)
        T_rgb = T_world_from_cam_at(plan, indoor.rig, plan.rgb_times_s[picks])
        T_depth = T_world_from_cam_at(plan, indoor.rig, plan.depth_times_s[picks])
        for i, k in enumerate(picks):
            a = time.perf_counter()
            image, _, _ = render_rgbd(
                scene,
                bank,
                T_rgb[i],
                T_depth[i],
                indoor.intrinsics,
                plan.lighting,
                cam,
                indoor.errors,
                indoor.render,
                np.random.default_rng(int(k)),
            )
            yield image, time.perf_counter() - a

    picks = np.arange(min(n_frames, len(plans[0].rgb_times_s)))
    t0 = time.perf_counter()
    for _ in frames(plans[0], picks):
        pass
    warmup_s = time.perf_counter() - t0
    ms = 1000 * float(np.mean([dt for _, dt in frames(plans[0], picks)]))
    orb_counts = {}
    for plan in plans:
        lap = np.linspace(0, len(plan.rgb_times_s) - 1, 24).astype(int)
        counts = [
            len(orb.detect(cv2.GaussianBlur(im, (5, 5), 0), None)) for im, _ in frames(plan, lap)
        ]
        orb_counts[plan.run] = {"mean": float(np.mean(counts)), "min": int(np.min(counts))}
    k = indoor.intrinsics
    result = {
        "indoor_frames": len(picks),
        "indoor_fps_per_core": 1000.0 / ms,
        "indoor_camera_depth_ms": ms,
        "indoor_warmup_ms_per_frame": 1000 * warmup_s / len(picks),
        "indoor_world_build_s": build_s,
        "indoor_resolution": [k.width_px, k.height_px],
        "indoor_orb_per_frame": orb_counts,
        "indoor_orb_target": INDOOR_ORB_TARGET,
    }
    rows = [
        (
            f"indoor frames/s per core (camera+depth {k.width_px}x{k.height_px})",
            f"{1000.0 / ms:.1f}",
            f"outdoor cam+depth {1000.0 / outdoor_camera_ms:.1f} (1241x376); >= {TARGET_FPS:.0f}",
        ),
        ("  indoor first pass ms/frame (textures)", f"{1000 * warmup_s / len(picks):.0f}", ""),
    ] + [
        (
            f"indoor ORB features/frame, {run} lap (min)",
            f"{v['mean']:.0f} ({v['min']})",
            f">= {INDOOR_ORB_TARGET}",
        )
        for run, v in orb_counts.items()
    ]
    return result, rows


if __name__ == "__main__":
    main()

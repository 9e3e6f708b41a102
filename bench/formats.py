"""COLMAP import: localization accuracy of the two ways an imported model's images get
their 3D points, next to the LiDAR-built map of the same run (the baseline), same queries.

A sim city's map run is written as a COLMAP model the way a user's would look: SIFT
keypoints (not ORB) observing 3D points (here from the run's LiDAR at those keypoints, in
place of triangulation, so the points are right and only the association differs), in a
KITTI-like world (-y up). It is imported twice (``--points orb``: ORB features take the
model's points by proximity to its 2D observations; ``--points model``: the model's
observations as they are, described with ORB), and the map run is also ingested from its
LiDAR. Every query frame is localized against each map (one frame, no filter: the best
hypothesis, and whether there is one). Prints the table, writes bench/results/formats.json.

Usage: python -m bench.formats [--size small] [--frames 120] [--seed 5] [--out out/bench_formats]
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).parent / "results"


def limit_threads() -> None:
    import cv2
    import faiss
    from threadpoolctl import threadpool_limits

    cv2.setNumThreads(1)
    faiss.omp_set_num_threads(1)
    threadpool_limits(1)


def ensure_dataset(root: Path, size: str, frames: int, seed: int) -> None:
    from monoloc.sim.generate import GenerateConfig, generate_dataset

    if (root / "dataset.json").exists():
        return
    print(f"generating a {size} sim city into {root} ({frames} frames per run) ...", flush=True)
    generate_dataset(
        GenerateConfig(size=size, seed=seed, runs=("map", "query"), max_frames=frames, workers=2),
        root,
    )


def write_sift_model(run, out: Path, n_sift: int = 2000) -> tuple[Path, Path, int]:
    """The map run as a COLMAP model of SIFT observations with LiDAR points (module doc)."""
    import cv2

    from monoloc.core.geometry import zup_to_kitti
    from monoloc.server.formats.colmap import write_colmap_model
    from monoloc.server.formats.model import ModelView
    from monoloc.server.vision.depth import points_from_lidar

    images_dir, model_dir = out / "images", out / "sparse"
    shutil.rmtree(out, ignore_errors=True)
    images_dir.mkdir(parents=True)
    sift = cv2.SIFT_create(nfeatures=n_sift)
    views, observations = [], 0
    for frame in run.frames:
        loaded = run.load(frame)
        keypoints_px = cv2.KeyPoint_convert(sift.detect(loaded.image_gray, None)).reshape(-1, 2)
        scan = loaded.source
        points_cam, has = points_from_lidar(
            keypoints_px.astype(np.float64),
            scan.points_lidar,
            scan.T_cam_from_lidar,
            run.intrinsics,
        )
        T_model_from_cam = zup_to_kitti(frame.T_world_from_cam)
        points_model = points_cam[has] @ T_model_from_cam[:3, :3].T + T_model_from_cam[:3, 3]
        name = f"{frame.index:06d}.png"
        shutil.copyfile(frame.image_path, images_dir / name)
        views.append(
            ModelView(name, run.intrinsics, T_model_from_cam, keypoints_px[has], points_model)
        )
        observations += int(has.sum())
    write_colmap_model(views, model_dir)
    return model_dir, images_dir, observations


def localize_all(registry, map_id: int, query) -> dict:
    from monoloc.core.geometry import planar_from_T_world_from_cam, wrap_angle
    from monoloc.server.localize import LocalizeConfig

    rng = np.random.default_rng(0)
    errors_m, errors_deg, found, times_ms = [], [], 0, []
    for frame in query.frames:
        truth = planar_from_T_world_from_cam(frame.T_world_from_cam)
        t0 = time.perf_counter()
        result, _ = registry.localize(map_id, query.load(frame).image_gray, LocalizeConfig(), rng)
        times_ms.append(1000 * (time.perf_counter() - t0))
        if result.best is None:
            continue
        found += 1
        errors_m.append(float(np.linalg.norm(result.best.pose_world[:2] - truth[:2])))
        errors_deg.append(abs(float(np.degrees(wrap_angle(result.best.pose_world[2] - truth[2])))))
    e = np.array(errors_m)
    return {
        "frames": len(query.frames),
        "with_hypothesis": found / len(query.frames),
        "position_rmse_m": float(np.sqrt(np.mean(e**2))) if len(e) else None,
        "position_median_m": float(np.median(e)) if len(e) else None,
        "within_0_25m": float(np.mean(e <= 0.25) * found / len(query.frames)) if len(e) else 0.0,
        "heading_median_deg": float(np.median(errors_deg)) if errors_deg else None,
        "localize_p50_ms": float(np.median(times_ms)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", default="small")
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("out/bench_formats"))
    args = parser.parse_args()
    limit_threads()

    from monoloc.server.formats.colmap import read_colmap_model
    from monoloc.server.formats.maps import import_sources_into_map
    from monoloc.server.formats.model import import_sources
    from monoloc.server.ingest.manage import create_map, ingest_source, map_stats
    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.server.map_registry import MapRegistry
    from monoloc.server.settings import Settings
    from monoloc.server.storage.db import create_engine_for, make_session_factory
    from monoloc.server.storage.migrate import upgrade_database

    root = args.out / f"city_{args.size}_{args.frames}_{args.seed}"
    ensure_dataset(root, args.size, args.frames, args.seed)
    map_run, query = read_kitti_sequence(root, "00"), read_kitti_sequence(root, "01")
    model_dir, images_dir, observations = write_sift_model(map_run, args.out / "colmap")
    data_dir = args.out / "data"
    shutil.rmtree(data_dir, ignore_errors=True)
    settings = Settings(data_dir=data_dir)
    upgrade_database(settings.database_url)
    factory = make_session_factory(create_engine_for(settings))

    rows = {}
    t0 = time.perf_counter()
    create_map(factory, "lidar", map_run.intrinsics)
    ingest_source(factory, "lidar", map_run)
    build_s = {"lidar": time.perf_counter() - t0}
    model = read_colmap_model(model_dir, images_dir)
    for points in ("orb", "model"):
        t0 = time.perf_counter()
        import_sources_into_map(
            factory, f"colmap-{points}", import_sources(model, fmt="colmap", up=None, points=points)
        )
        build_s[f"colmap-{points}"] = time.perf_counter() - t0
    registry = MapRegistry(factory, settings.index_dir)
    for name in ("lidar", "colmap-orb", "colmap-model"):
        stats = map_stats(factory, name)
        row = localize_all(registry, stats.record.id, query)
        row.update(
            entries=stats.record.n_entries,
            points_per_entry=stats.points_mean,
            build_s=build_s[name],
        )
        rows[name] = row

    print(
        f"\nCOLMAP import, {args.size} sim city seed {args.seed}: map run {len(map_run.frames)} "
        f"frames ({observations / len(map_run.frames):.0f} SIFT observations with a 3D point "
        f"per image), query run {len(query.frames)} frames, one frame at a time, no filter"
    )
    header = (
        f"{'map':<18}{'entries':>8}{'pts/entry':>10}{'hyp. %':>8}{'RMSE m':>9}"
        f"{'median m':>10}{'<=0.25m %':>10}{'head. deg':>10}{'build s':>9}"
    )
    print(header)
    for name, r in rows.items():
        label = name + (" (baseline)" if name == "lidar" else "")

        def fmt(v, spec):
            return format(v, spec) if v is not None else "-"

        print(
            f"{label:<18}{r['entries']:>8}{r['points_per_entry']:>10.0f}"
            f"{100 * r['with_hypothesis']:>8.0f}{fmt(r['position_rmse_m'], '>9.3f')}"
            f"{fmt(r['position_median_m'], '>10.3f')}{100 * r['within_0_25m']:>10.0f}"
            f"{fmt(r['heading_median_deg'], '>10.2f')}{r['build_s']:>9.1f}"
        )
    RESULTS.mkdir(exist_ok=True)
    out = RESULTS / "formats.json"
    out.write_text(
        json.dumps(
            {
                "bench": "formats",
                "dataset": {"size": args.size, "frames": args.frames, "seed": args.seed},
                "sift_observations_per_image": observations / len(map_run.frames),
                "maps": rows,
                "baseline": "lidar",
            },
            indent=2,
        )
        + "\n"
    )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

"""Maps from a stereo camera vs maps from the LiDAR, on the same sim runs (issue 18 item 5).

One sim city recorded with both the LiDAR and the right camera (image_1, KITTI's 0.54 m
baseline) and the renderer's exact depth. The same `map` run is built into two maps, one
with keypoint depth from the LiDAR (the baseline), one from stereo (SGBM,
``monoloc.server.vision.stereo``); each map's measurement model is calibrated on the
`train` run with the same depth source; the same `query` run is localized against both
(full method). Prints, LiDAR beside stereo: the share of ORB keypoints that get a depth,
their depth error against the rendered depth (all keypoints, and those on smooth
surfaces), ingestion time per frame, entries, localization RMSE / median / heading /
share within 0.25 m and 2 deg. Writes bench/results/stereo.json.

    python -m bench.stereo [--size medium] [--frames 400] [--seed 1013]

bench/accuracy.py calls ``compare`` on its own city (same size, frames and seed).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).parent / "results"
SOURCES = ("lidar", "stereo")


def ensure_stereo_dataset(root: Path, size: str, frames: int, seed: int) -> dict:
    """The city's map, query and train runs with LiDAR, right camera and exact depth."""
    from monoloc.sim.generate import GenerateConfig, generate_dataset

    if (root / "dataset.json").exists():
        return json.loads((root / "dataset.json").read_text())
    print(f"generating a {size} city with stereo into {root} ({frames} frames per run) ...")
    t0 = time.time()
    config = GenerateConfig(
        size=size,
        seed=seed,
        runs=("map", "query", "train"),
        max_frames=frames,
        write_depth=True,
        write_stereo=True,
        workers=2,
    )
    generate_dataset(config, root)
    print(f"  done in {time.time() - t0:.0f} s", flush=True)
    return json.loads((root / "dataset.json").read_text())


def depth_quality(seq_lidar, seq_stereo, every: int = 5) -> dict:
    """Share of ORB keypoints with a depth and the depth's relative error against the
    rendered depth, per source, on every ``every``-th frame of the map run."""
    from monoloc.server.entry_builder import BuildConfig, points_for
    from monoloc.server.vision.features import OrbConfig, extract_features
    from monoloc.sim.depth_truth import rendered_depth_at
    from monoloc.sim.kitti_writer import read_depth

    stats = {s: {"share": [], "rel_all": [], "rel_smooth": []} for s in SOURCES}
    seqs = dict(zip(SOURCES, (seq_lidar, seq_stereo), strict=True))
    for fl, fs in list(zip(seq_lidar.frames, seq_stereo.frames, strict=True))[::every]:
        frames = {"lidar": (seq_lidar, fl), "stereo": (seq_stereo, fs)}
        truth_path = fl.image_path.parent.parent / "depth" / fl.image_path.name
        truth_image = read_depth(truth_path)
        for source in SOURCES:
            seq, frame = frames[source]
            loaded = seq.load(frame)
            features = extract_features(loaded.image_gray, OrbConfig())
            points, has = points_for(
                features, loaded.source, seqs[source].intrinsics, BuildConfig(), loaded.image_gray
            )
            truth, smooth = rendered_depth_at(features.keypoints_px, truth_image)
            with np.errstate(invalid="ignore"):  # sky: the rendered depth is inf
                rel = np.abs(points[:, 2] - truth) / truth
            stats[source]["share"].append(float(has.mean()))
            stats[source]["rel_all"].append(rel[has & np.isfinite(truth)])
            stats[source]["rel_smooth"].append(rel[has & smooth & np.isfinite(truth)])
    out = {}
    for source, s in stats.items():
        rel_all, rel_smooth = np.concatenate(s["rel_all"]), np.concatenate(s["rel_smooth"])
        out[source] = {
            "keypoints_with_depth": float(np.mean(s["share"])),
            "rel_error_median": float(np.median(rel_all)),
            "rel_error_p90": float(np.percentile(rel_all, 90)),
            "share_error_over_10pct": float(np.mean(rel_all > 0.10)),
            "smooth_rel_error_median": float(np.median(rel_smooth)),
            "smooth_share_error_over_10pct": float(np.mean(rel_smooth > 0.10)),
            "smooth_keypoints": int(len(rel_smooth)),
        }
    return out


def compare(root: Path, meta: dict, lever_arm_m: float | None = None) -> dict:
    """Build the LiDAR and the stereo map of the `map` run, calibrate each on `train`,
    localize `query` against each; print and return the figures."""
    from bench.lab.evaluation import MemoryMap, evaluate_run, metrics_row
    from monoloc.client.replay import read_kitti_run, rig_lever_arm_m
    from monoloc.server.calibrate import CalibrationConfig, calibrate
    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.server.jobs.calibration import training_frames
    from monoloc.server.vision.vocabulary import load_default_vocabulary

    ids = {s["run"]: s["id"] for s in meta["sequences"]}
    vocab = load_default_vocabulary()
    lever = lever_arm_m if lever_arm_m is not None else rig_lever_arm_m(root)
    query_signals = read_kitti_run(root, ids["query"]).signals
    out: dict = {"runs": ids}
    seqs = {s: read_kitti_sequence(root, ids["map"], depth_from=s) for s in SOURCES}
    out["depth"] = depth_quality(seqs["lidar"], seqs["stereo"])
    for source in SOURCES:
        t0 = time.time()
        train = read_kitti_sequence(root, ids["train"], depth_from=source)
        model = calibrate(
            training_frames(train),
            train.intrinsics,
            vocab,
            CalibrationConfig(),
            np.random.default_rng(0),
            source_name=f"train ({source})",
        ).model
        t_cal = time.time() - t0
        memory = MemoryMap.empty(vocab)
        t0 = time.time()
        added = memory.add_run(seqs[source])
        t_map = time.time() - t0
        query = read_kitti_sequence(root, ids["query"], depth_from=source)
        result = evaluate_run(
            memory, query, query_signals, model, lever_arm_m=lever, variants=("full", "best_pnp")
        )
        n_points = [len(r.points_cam) for r in memory.refs.values()]
        out[source] = {
            "entries": added,
            "skipped_frames": memory.skipped,
            "points_per_entry_mean": float(np.mean(n_points)) if n_points else 0.0,
            "map_build_s_per_frame": t_map / max(len(seqs[source].frames), 1),
            "calibration_s": t_cal,
            "query": {v: metrics_row(m) for v, m in result.metrics.items()},
        }
        print(f"{source}: map {added} entries in {t_map:.0f} s, calibrated in {t_cal:.0f} s")
    print_table(out)
    return out


def print_table(out: dict) -> None:
    d, lid, ste = out["depth"], out["lidar"], out["stereo"]
    print(f"\n{'stereo map vs LiDAR map, same runs':<44}{'LiDAR':>12}{'stereo':>12}")
    rows = [
        ("ORB keypoints with a depth", "keypoints_with_depth", "{:.1%}", d),
        ("depth error vs rendered, median", "rel_error_median", "{:.2%}", d),
        ("depth error, 90th percentile", "rel_error_p90", "{:.1%}", d),
        ("depths off by > 10 %", "share_error_over_10pct", "{:.1%}", d),
        ("  on smooth surfaces: median", "smooth_rel_error_median", "{:.2%}", d),
        ("  on smooth surfaces: off by > 10 %", "smooth_share_error_over_10pct", "{:.1%}", d),
    ]
    for name, key, fmt, src in rows:
        print(f"{name:<44}{fmt.format(src['lidar'][key]):>12}{fmt.format(src['stereo'][key]):>12}")
    for name, key, fmt in (
        ("map entries", "entries", "{}"),
        ("3D points per entry", "points_per_entry_mean", "{:.0f}"),
        ("map build per frame (s, one thread)", "map_build_s_per_frame", "{:.3f}"),
    ):
        print(f"{name:<44}{fmt.format(lid[key]):>12}{fmt.format(ste[key]):>12}")
    for variant in ("full", "best_pnp"):
        a, b = lid["query"][variant], ste["query"][variant]
        for name, key, fmt in (
            ("position RMSE (m)", "position_rmse_m", "{:.3f}"),
            ("position median (m)", "position_median_m", "{:.3f}"),
            ("heading RMSE (deg)", "heading_rmse_deg", "{:.2f}"),
            ("within 0.25 m / 2 deg", "within_0_25m_2deg", "{:.1%}"),
            ("frames with an estimate", "coverage", "{:.0%}"),
        ):
            va, vb = a.get(key), b.get(key)
            sa = "-" if va is None else fmt.format(va)
            sb = "-" if vb is None else fmt.format(vb)
            print(f"{f'query, {variant}: {name}':<44}{sa:>12}{sb:>12}")


def main() -> None:
    from bench.accuracy import HELD_OUT_SEED, limit_threads

    parser = argparse.ArgumentParser()
    parser.add_argument("--size", default="medium")
    parser.add_argument("--frames", type=int, default=400)
    parser.add_argument("--seed", type=int, default=HELD_OUT_SEED)
    parser.add_argument("--data", type=Path, default=Path(__file__).parent / "data")
    args = parser.parse_args()
    limit_threads()
    root = args.data / f"urban_{args.size}_{args.frames}_s{args.seed}_stereo"
    meta = ensure_stereo_dataset(root, args.size, args.frames, args.seed)
    out = {"size": args.size, "frames_per_run": args.frames, "seed": args.seed}
    out.update(compare(root, meta))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "stereo.json").write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()

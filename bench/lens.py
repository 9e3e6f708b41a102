"""The server's time per query of a distorted query against a pinhole one of the same
frames (issue 48: within 10 %).

The sim's fleet run (bench/fleet_camera.py: the query's drive by issue 48's fleet camera,
1024x576, plumb_bob k1 -0.28) against the map of its ``map`` run. Each frame is localized
twice per pass, interleaved, with the same RANSAC seed: raw, distorted, with its lens
model (the server undistorts its keypoints), and the same frame undistorted to a pinhole
image of the same K beforehand (not timed; the baseline), sent as a pinhole camera. The
time is the localization stage's CPU time on this thread (``localize_frame``: features,
VLAD, retrieval, matching, PnP; no prior, one core); per frame the median over the
passes. Beside it, the keypoint undistortion alone on the frames' own keypoints.
HTTP decoding and the stream are the same for both and are left out.
Usage: python -m bench.lens [--size small] [--frames 150] [--queries 60] [--passes 3]
Writes bench/results/lens.json (another ``--fleet-camera``: lens_<camera>.json).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from bench.accuracy import HELD_OUT_SEED, RESULTS, limit_threads, sequence_of
from bench.fleet_camera import UndistortedSource, ensure_fleet_dataset, fleet_camera_of

GOAL_DISTORTED_OVER_PINHOLE = 1.10


def _cpu_ms(fn) -> tuple[object, float]:
    started = time.thread_time()
    out = fn()
    return out, (time.thread_time() - started) * 1e3


def measure(root: Path, meta: dict, queries: int, passes: int) -> dict:
    from bench.lab.evaluation import MemoryMap
    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.server.localize import LocalizeConfig, localize_frame
    from monoloc.server.vision.features import extract_features
    from monoloc.server.vision.undistort import undistort_pixels
    from monoloc.server.vision.vocabulary import load_default_vocabulary

    vocab = load_default_vocabulary()
    memory = MemoryMap.empty(vocab)
    memory.add_run(read_kitti_sequence(root, sequence_of(meta, "map")))
    fleet_id = sequence_of(meta, "fleet")
    camera, _ = fleet_camera_of(root, fleet_id)
    raw = read_kitti_sequence(root, fleet_id)
    undistorted = UndistortedSource.of(raw, camera)
    frames = raw.frames[:: max(1, raw.n_frames // queries)][:queries]
    config = LocalizeConfig()
    print(
        f"map: {len(memory.refs)} entries; {len(frames)} fleet frames x {passes} passes, "
        f"camera {camera.width_px}x{camera.height_px} {camera.distortion.model}",
        flush=True,
    )

    def run(image, intrinsics, seed):
        return localize_frame(
            image, intrinsics, vocab, memory.index, memory.lookup, config,
            np.random.default_rng(seed),
        )  # fmt: skip

    images = [(raw.load(f).image_gray, undistorted.load(f).image_gray) for f in frames]
    run(images[0][0], camera, 0)  # warm-up: numba kernels, caches
    run(images[0][1], camera.pinhole, 0)
    total = {
        "distorted": np.zeros((len(frames), passes)),
        "pinhole": np.zeros((len(frames), passes)),
    }
    features = {
        "distorted": np.zeros((len(frames), passes)),
        "pinhole": np.zeros((len(frames), passes)),
    }
    wall = {
        "distorted": np.zeros((len(frames), passes)),
        "pinhole": np.zeros((len(frames), passes)),
    }
    hypotheses = {"distorted": [], "pinhole": []}
    for p in range(passes):
        for i, (distorted_image, pinhole_image) in enumerate(images):
            order = [
                ("distorted", distorted_image, camera),
                ("pinhole", pinhole_image, camera.pinhole),
            ]
            for name, image, intrinsics in order if (i + p) % 2 == 0 else order[::-1]:
                seed = 1000 * p + i
                result, ms = _cpu_ms(lambda im=image, k=intrinsics, s=seed: run(im, k, s))
                total[name][i, p] = ms
                features[name][i, p] = result.timings_ms["features"]
                wall[name][i, p] = result.timings_ms["total"]
                if p == 0:
                    hypotheses[name].append(len(result.hypotheses))
    # the undistortion alone, on each distorted frame's own keypoints
    undistort_us = []
    for distorted_image, _ in images:
        keypoints = extract_features(distorted_image, config.orb).keypoints_px
        _, ms = _cpu_ms(lambda kp=keypoints: [undistort_pixels(kp, camera) for _ in range(20)])
        undistort_us.append(ms / 20 * 1e3)
    per_frame = {name: np.median(t, axis=1) for name, t in total.items()}
    stats = {
        name: {
            "mean_ms": float(np.mean(t)),
            "p50_ms": float(np.median(t)),
            "p90_ms": float(np.percentile(t, 90)),
            # wall-clock (the stage laps' clock), on a machine others may share
            "wall_p50_ms": float(np.median(np.median(wall[name], axis=1))),
            "features_stage_wall_p50_ms": float(np.median(np.median(features[name], axis=1))),
            "mean_hypotheses": float(np.mean(hypotheses[name])),
        }
        for name, t in per_frame.items()
    }
    ratio_mean = stats["distorted"]["mean_ms"] / stats["pinhole"]["mean_ms"]
    ratio_p50 = stats["distorted"]["p50_ms"] / stats["pinhole"]["p50_ms"]
    paired = per_frame["distorted"] / per_frame["pinhole"]
    return {
        "camera": {
            "width_px": camera.width_px,
            "height_px": camera.height_px,
            "fx": camera.fx,
            "distortion_model": camera.distortion.model,
            "D": list(camera.distortion.coefficients),
        },
        "frames": len(frames),
        "passes": passes,
        "per_query": stats,
        "distorted_over_pinhole_mean": ratio_mean,
        "distorted_over_pinhole_p50": ratio_p50,
        "distorted_over_pinhole_paired_median": float(np.median(paired)),
        "undistort_keypoints_us_p50": float(np.median(undistort_us)),
        "goal_distorted_over_pinhole": GOAL_DISTORTED_OVER_PINHOLE,
        "goal_met": bool(ratio_mean <= GOAL_DISTORTED_OVER_PINHOLE),
    }


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--size", default="small")
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--seed", type=int, default=HELD_OUT_SEED)
    parser.add_argument("--fleet-camera", default="issue48")
    parser.add_argument("--data", type=Path, default=Path(__file__).parent / "data")
    parser.add_argument("--queries", type=int, default=60)
    parser.add_argument("--passes", type=int, default=3)
    args = parser.parse_args()
    limit_threads()
    root = args.data / f"fleet_{args.size}_{args.frames}_s{args.seed}_{args.fleet_camera}"
    meta = ensure_fleet_dataset(root, args.size, args.frames, args.seed, args.fleet_camera)
    out = {"size": args.size, "seed": args.seed, "fleet_camera": args.fleet_camera}
    out.update(measure(root, meta, args.queries, args.passes))
    s = out["per_query"]
    print(
        f"{'query (CPU ms; wall ms)':<34}{'mean':>8}{'p50':>8}{'p90':>8}{'wall p50':>10}"
        f"{'features wall':>15}{'hyp':>6}"
    )
    labels = {"distorted": "distorted, lens model sent", "pinhole": "same frames undistorted first"}
    for name, label in labels.items():
        r = s[name]
        print(
            f"{label:<34}{r['mean_ms']:>8.2f}{r['p50_ms']:>8.2f}{r['p90_ms']:>8.2f}"
            f"{r['wall_p50_ms']:>10.2f}{r['features_stage_wall_p50_ms']:>15.2f}"
            f"{r['mean_hypotheses']:>6.1f}"
        )
    verdict = "met" if out["goal_met"] else "MISSED"
    print(
        f"distorted / pinhole: mean {out['distorted_over_pinhole_mean']:.3f}x, p50 "
        f"{out['distorted_over_pinhole_p50']:.3f}x, paired per-frame median "
        f"{out['distorted_over_pinhole_paired_median']:.3f}x (goal <= "
        f"{GOAL_DISTORTED_OVER_PINHOLE}x: {verdict}); undistorting a frame's keypoints "
        f"{out['undistort_keypoints_us_p50']:.0f} us"
    )
    RESULTS.mkdir(exist_ok=True)
    name = "" if args.fleet_camera == "issue48" else f"_{args.fleet_camera}"
    (RESULTS / f"lens{name}.json").write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()

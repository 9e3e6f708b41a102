"""What each recording error costs the localizer: the sim's errors turned on one group at a
time (issue 13 item 4's errors; `docs/sim.md`).

For each seed and each group of the sim's recording errors (`RecordingErrors.only`: none,
all, the INS pose errors, the LiDAR-camera calibration, the LiDAR's timing, the vehicle
signals, the camera, all but the calibration), one small city is recorded (map, query and
train runs), the measurement model calibrated on `train`, the `map` run mapped and the `query`
run localized with the default filter. Printed per group, against the map's own frame
(`truth_in_map_frame`: what the recording errors of the map's poses cannot explain away):
the filter's median error, the best of the frame's hypotheses picked with the truth (the
oracle of issue 13's filter / best-of-k goal), the likeliest hypothesis, and their ratio;
against the written truth, the filter's RMSE and median beside the floor (a pose exact
relative to the map). Writes bench/results/error_split.json (``--out`` names another:
results/error_split_medium_s8807.json is `--size medium --frames 300 --seeds 8807`).

    python -m bench.error_split [--seeds 23 42] [--groups none all calibration] (about 7
    minutes a seed on 2 cores)
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from bench.accuracy import (
    calibrate_on,
    fitted_lever_arm_m,
    limit_threads,
    sequence_of,
    written_poses,
)

RESULTS = Path(__file__).parent / "results"

# each row of the split: the groups of `RecordingErrors.only` it turns on
SOURCES = ("pose", "calibration", "lidar_timing", "signals", "camera")
GROUPS = {
    "none": (),
    "all": SOURCES,
    **{source: (source,) for source in SOURCES},
    "all_but_calibration": tuple(s for s in SOURCES if s != "calibration"),
}


def measure(group: str, seed: int, size: str, frames: int, data: Path) -> dict:
    """One city with the group's errors: the figures of the module docstring."""
    from bench.lab.evaluation import MemoryMap, evaluate_run
    from monoloc.client.replay import read_kitti_run, rig_lever_arm_m
    from monoloc.client.trajectory import best_of_k_errors, truth_in_map_frame
    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.server.vision.vocabulary import load_default_vocabulary
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.recording import RecordingErrors
    from monoloc.sim.urban.truth import true_planar_poses

    config = GenerateConfig(
        size=size,
        seed=seed,
        runs=("map", "query", "train"),
        max_frames=frames,
        errors=RecordingErrors.only(*GROUPS[group]),
        workers=2,
    )
    root = data / f"errors_{group}_{size}_{frames}_s{seed}"
    if not (root / "dataset.json").exists():
        generate_dataset(config, root)
    meta = json.loads((root / "dataset.json").read_text())
    ids = {run: sequence_of(meta, run) for run in ("map", "query", "train")}
    true_world = true_planar_poses(config, np.array(meta["T_simworld_from_zupworld"]))
    vocab = load_default_vocabulary()
    lever = fitted_lever_arm_m(read_kitti_run(root, ids["train"]), rig_lever_arm_m(root))
    model = calibrate_on(read_kitti_sequence(root, ids["train"]), vocab).model
    memory = MemoryMap.empty(vocab)
    memory.add_run(read_kitti_sequence(root, ids["map"]))
    query = read_kitti_sequence(root, ids["query"])
    signals = read_kitti_run(root, ids["query"]).signals
    result = evaluate_run(memory, query, signals, model, lever_arm_m=lever, variants=("full",))
    placed = truth_in_map_frame(
        true_world["query"], true_world["map"], written_poses(root, ids["map"])
    )
    estimate = result.estimates["full"]
    filter_map = np.linalg.norm(estimate[:, :2] - placed[:, :2], axis=1)
    best_map = best_of_k_errors(result.hypotheses_world, placed)
    likeliest_map = np.linalg.norm(result.likeliest_world[:, :2] - placed[:, :2], axis=1)
    filter_written = np.linalg.norm(estimate[:, :2] - result.truth_world[:, :2], axis=1)
    floor = np.linalg.norm(placed[:, :2] - result.truth_world[:, :2], axis=1)
    both = np.isfinite(best_map) & np.isfinite(filter_map)
    written = np.isfinite(filter_written)
    return {
        "group": group,
        "seed": seed,
        "frames_with_hypotheses": int(both.sum()),
        "filter_map_median_m": float(np.median(filter_map[both])),
        "best_of_k_map_median_m": float(np.median(best_map[both])),
        "likeliest_map_median_m": float(np.median(likeliest_map[both])),
        "filter_over_best_of_k_map": float(
            np.median(filter_map[both]) / max(np.median(best_map[both]), 1e-9)
        ),
        "filter_rmse_m": float(np.sqrt(np.mean(filter_written[written] ** 2))),
        "filter_median_m": float(np.median(filter_written[written])),
        "floor_median_m": float(np.median(floor)),
    }


def print_rows(rows: list[dict]) -> None:
    print(
        f"\n{'errors on':<22}{'seed':>5}{'filter mm':>10}{'best k mm':>10}{'likeliest':>10}"
        f"{'ratio':>7}  | written truth: {'RMSE m':>7}{'median m':>9}{'floor m':>8}"
    )
    for r in rows:
        print(
            f"{r['group']:<22}{r['seed']:>5}{r['filter_map_median_m'] * 1000:>10.1f}"
            f"{r['best_of_k_map_median_m'] * 1000:>10.1f}"
            f"{r['likeliest_map_median_m'] * 1000:>10.1f}{r['filter_over_best_of_k_map']:>7.2f}"
            f"  |                {r['filter_rmse_m']:>7.3f}{r['filter_median_m']:>9.3f}"
            f"{r['floor_median_m']:>8.3f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[23, 42])
    parser.add_argument("--groups", nargs="+", choices=list(GROUPS), default=list(GROUPS))
    parser.add_argument("--size", default="small")
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--data", type=Path, default=Path(__file__).parent / "data")
    parser.add_argument(
        "--out",
        default="error_split",
        help="results/<out>.json; REPORT.md shows error_split.json and every error_split_*.json",
    )
    args = parser.parse_args()
    limit_threads()
    rows = []
    for seed in args.seeds:
        for group in args.groups:
            t0 = time.time()
            rows.append(measure(group, seed, args.size, args.frames, args.data))
            print(f"{group}, seed {seed}: {time.time() - t0:.0f} s", flush=True)
    print_rows(rows)
    out = {"size": args.size, "frames_per_run": args.frames, "rows": rows}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{args.out}.json").write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()

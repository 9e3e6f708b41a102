"""Accuracy of the method on a sim city (and its night) or the indoor track, by variant.

Generates (or reuses) a sim dataset, builds the map in memory with the server's own
code, calibrates the measurement model on the `train` run (a district the map and the
query never see), and localizes the `query` run with each variant of
monoloc.evaluation. With a `nightmap` run in the dataset, the `night` query is run twice:
against the day map, and after adding the night entries. Prints the table next to the
paper's numbers and the goals; writes bench/results/accuracy_<scenario>.json.
Indoor (`--scenario indoor`): the 1:10 car's query lap against the map lap, then against
the map plus the off-center lap (the paper's augmentation), next to the paper's indoor
open-loop figures.
Usage: python bench/accuracy.py [--scenario urban|indoor] [--size medium] [--frames 400]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).parent / "results"
PAPER = {"position_rmse_m": 0.313, "note": "KITTI 00, 85 % map / 15 % test"}
GOALS = {"position_rmse_m": 0.15, "heading_rmse_deg": 0.5, "within_0_25m_2deg": 0.90}


def limit_threads() -> None:
    import cv2
    import faiss
    from threadpoolctl import threadpool_limits

    cv2.setNumThreads(1)
    faiss.omp_set_num_threads(1)
    threadpool_limits(1)


def ensure_dataset(
    root: Path, size: str, frames: int, seed: int, runs: tuple[str, ...], scenario: str = "urban"
):
    from monoloc.sim.generate import GenerateConfig, generate_dataset

    if (root / "dataset.json").exists():
        return json.loads((root / "dataset.json").read_text())
    print(
        f"generating a {size} {scenario} world into {root} ({frames} frames per run) ...",
        flush=True,
    )
    t0 = time.time()
    generate_dataset(
        GenerateConfig(
            scenario=scenario, size=size, seed=seed, runs=runs, max_frames=frames, workers=2
        ),
        root,
    )
    print(f"  done in {time.time() - t0:.0f} s", flush=True)
    return json.loads((root / "dataset.json").read_text())


def calibrate_on(train, vocabulary):
    """The measurement model fitted on a training run (KittiSequence / TumRun), each frame
    read once, exactly as the server's calibration job does."""
    from monoloc.server.calibrate import CalibrationConfig, calibrate
    from monoloc.server.jobs.calibration import training_frames

    return calibrate(
        training_frames(train),
        train.intrinsics,
        vocabulary,
        CalibrationConfig(),
        np.random.default_rng(0),
        source_name="train",
    )


def sequence_of(meta: dict, run: str) -> str | None:
    for seq in meta["sequences"]:
        if seq["run"] == run:
            return seq["id"]
    return None


def print_table(rows: list[tuple[str, dict]]) -> None:
    head = (
        f"{'variant':<28}{'frames':>7}{'RMSE m':>8}{'median m':>10}{'head deg':>9}{'<.25m/2°':>10}"
        f"{'<.5m/5°':>9}{'<5m/10°':>9}"
    )
    print(head)

    def f(x, spec):
        return format(x, spec) if x is not None else format("-", ">" + spec.split(".")[0])

    for name, m in rows:
        print(
            f"{name:<28}{100 * m['coverage']:>6.0f}%{f(m['position_rmse_m'], '8.3f')}"
            f"{f(m['position_median_m'], '10.3f')}{f(m['heading_rmse_deg'], '9.2f')}"
            f"{100 * m['within_0_25m_2deg']:>9.1f}%"
            f"{100 * m['within_0_5m_5deg']:>8.1f}%{100 * m['within_5m_10deg']:>8.1f}%"
        )


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--scenario", default="urban", choices=("urban", "indoor"))
    parser.add_argument("--size", default="medium")
    parser.add_argument("--frames", type=int, default=400)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--data", type=Path, default=Path(__file__).parent / "data")
    args = parser.parse_args()
    limit_threads()
    if args.scenario == "indoor":
        return main_indoor(args)
    from monoloc.client.replay import read_kitti_run, rig_lever_arm_m
    from monoloc.core.measurement import MeasurementModel
    from monoloc.evaluation import MemoryMap, evaluate_run, metrics_row, stage_percentiles
    from monoloc.server.ingest.kitti import read_kitti_sequence
    from monoloc.server.vision.vocabulary import load_default_vocabulary

    root = args.data / f"urban_{args.size}_{args.frames}_s{args.seed}"
    meta = ensure_dataset(
        root, args.size, args.frames, args.seed, ("map", "query", "train", "night", "nightmap")
    )
    vocab = load_default_vocabulary()
    lever = rig_lever_arm_m(root) or 0.0
    t0 = time.time()
    train = read_kitti_sequence(root, sequence_of(meta, "train"))
    calib = calibrate_on(train, vocab)
    model: MeasurementModel = calib.model
    print(f"calibrated on {calib.provenance['used']} hypotheses in {time.time() - t0:.0f} s")
    memory = MemoryMap.empty(vocab)
    t0 = time.time()
    memory.add_run(read_kitti_sequence(root, sequence_of(meta, "map")))
    print(f"map: {len(memory.refs)} entries in {time.time() - t0:.0f} s")
    query_id = sequence_of(meta, "query")
    query = read_kitti_sequence(root, query_id)
    signals = read_kitti_run(root, query_id).signals
    result = evaluate_run(memory, query, signals, model, lever_arm_m=lever)
    rows = [(v, metrics_row(m)) for v, m in result.metrics.items()]
    out = {
        "scenario": "urban",
        "size": args.size,
        "frames_per_run": args.frames,
        "calibration": {"model": model.to_dict(), "provenance": calib.provenance},
        "query": dict(rows),
        "stages_ms": stage_percentiles(result.timings_ms),
        "paper": PAPER,
        "goals": GOALS,
    }
    night_id, nightmap_id = sequence_of(meta, "night"), sequence_of(meta, "nightmap")
    night_rows = []
    if night_id:
        night = read_kitti_sequence(root, night_id)
        nsig = read_kitti_run(root, night_id).signals
        before = evaluate_run(memory, night, nsig, model, lever_arm_m=lever, variants=("full",))
        night_rows.append(("night, day map", metrics_row(before.metrics["full"])))
        if nightmap_id:
            added = memory.add_run(read_kitti_sequence(root, nightmap_id), tags=("night",))
            after = evaluate_run(memory, night, nsig, model, lever_arm_m=lever, variants=("full",))
            night_rows.append(
                (f"night, +{added} night entries", metrics_row(after.metrics["full"]))
            )
    out["night"] = dict(night_rows)
    print_table(rows + night_rows)
    print(
        f"paper (KITTI 00): RMSE {PAPER['position_rmse_m']} m; goals: RMSE <= 0.15 m, "
        "heading <= 0.5 deg, >= 90 % within 0.25 m / 2 deg"
    )
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "accuracy_urban.json").write_text(json.dumps(out, indent=2) + "\n")


PAPER_INDOOR = {"open_loop_within_0_1m": 1.0, "open_loop_within_0_06m": 0.92}


def main_indoor(args) -> None:
    from monoloc.client.replay import read_tum_run as read_tum_replay
    from monoloc.client.replay import rig_lever_arm_m
    from monoloc.evaluation import MemoryMap, evaluate_run, metrics_row, stage_percentiles
    from monoloc.server.ingest.tum import read_tum_run
    from monoloc.server.vision.vocabulary import load_default_vocabulary

    root = args.data / f"indoor_{args.size}_{args.frames}_s{args.seed}"
    ensure_dataset(
        root,
        args.size,
        args.frames,
        args.seed,
        ("map", "query", "train", "offcenter"),
        scenario="indoor",
    )
    vocab = load_default_vocabulary()
    lever = rig_lever_arm_m(root / "map") or 0.0
    train = read_tum_run(root / "train")
    calib = calibrate_on(train, vocab)
    memory = MemoryMap.empty(vocab)
    memory.add_run(read_tum_run(root / "map"))
    query = read_tum_run(root / "query")
    signals = read_tum_replay(root / "query").signals
    base = evaluate_run(memory, query, signals, calib.model, lever_arm_m=lever)
    rows = [(v, metrics_row(m)) for v, m in base.metrics.items()]
    memory.add_run(read_tum_run(root / "offcenter"), tags=("off-center",))
    aug = evaluate_run(memory, query, signals, calib.model, lever_arm_m=lever, variants=("full",))
    rows.append(("full, map + off-center lap", metrics_row(aug.metrics["full"])))
    est, truth = base.estimates["full"], base.truth_world
    err = np.linalg.norm(est[:, :2] - truth[:, :2], axis=1)
    shares = {"within_0_1m": float(np.mean(err < 0.1)), "within_0_06m": float(np.mean(err < 0.06))}
    print_table(rows)
    print(
        f"full method: {100 * shares['within_0_1m']:.1f} % of frames < 0.1 m, "
        f"{100 * shares['within_0_06m']:.1f} % < 0.06 m (paper, real 1:10 car, open loop: "
        "100 % < 0.1 m, ~92 % < 0.06 m)"
    )
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "accuracy_indoor.json").write_text(
        json.dumps(
            {
                "scenario": "indoor",
                "size": args.size,
                "frames_per_run": args.frames,
                "calibration": {"model": calib.model.to_dict(), "provenance": calib.provenance},
                "query": dict(rows),
                "full_error_shares": shares,
                "paper": PAPER_INDOOR,
                "stages_ms": stage_percentiles(base.timings_ms),
            },
            indent=2,
        )
        + "\n"
    )


if __name__ == "__main__":
    main()

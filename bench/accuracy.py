"""Accuracy of the method on a sim city (and its night) or the indoor track, by variant.

Generates (or reuses) a sim dataset, builds the map in memory with the server's own
code, calibrates the measurement model on the `train` run (a district the map and the
query never see; with a `trainnight` run, the quality-aware model also on both together,
run beside the default), and localizes the `query` run with each variant of
bench.lab.evaluation: the default (the PnP covariance model, the server's alternative poses),
and beside it the paper's covariance (with and without monoloc's tail) and the PnP
covariance model without the alternative poses. With a
`nightmap` run in the dataset, the `night` query is run twice:
against the day map, and after adding the night entries. Prints the table next to the
paper's numbers and the goals; writes bench/results/accuracy_<scenario>.json.
Then (unless `--no-stereo`) the same city recorded with a stereo camera: a map built with
stereo depth against the LiDAR-built map of the same run, same query (bench/stereo.py).
Indoor (`--scenario indoor`): the 1:10 car's query lap against the map lap, then against
the map plus the off-center lap (the paper's augmentation), next to the paper's indoor
open-loop figures.
A fleet car's camera (`--scenario fleet`, bench/fleet_camera.py): the query's drive
recorded by another camera (size, focal length, lens, mounting; `--fleet-camera`), raw
and undistorted, beside the mapping camera's lap (issue 48); writes
bench/results/accuracy_fleet.json.
Usage: python -m bench.accuracy [--scenario urban|indoor|fleet] [--size medium] [--frames 300]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).parent / "results"
PAPER = {"position_rmse_m": 0.313, "note": "KITTI 00, 85 % map / 15 % test"}
# Issue 13 item 5: medium city, recording errors on, query run.
GOALS = {
    "position_rmse_m": 0.07,
    "position_median_m": 0.04,
    "heading_rmse_deg": 0.3,
    "within_0_25m_2deg": 0.98,
    "night_rmse_over_day": 1.5,
    "filter_median_over_best_of_k": 1.2,
}
# The held-out city: a seed no developer had tuned on when it was first run. Seeds used
# while developing: 0 (bench/localize, speed, ingest, sim), 3 (the demo), 5, 42 and the
# medium 23, 29 (issue 13's model choices), 6 (an earlier held-out city), 7 (this bench
# before issue 13), 41 (issue 13's filter work: the bias analysis and the before/after
# runs), 1013 (the held-out city until 2026-11-28, spent: its figures were seen before
# the defaults changed; results/accuracy_urban_s1013.json). 4099: first run on
# 2026-11-28 on the code of 57a9e95, untouched before; its night was diagnosed after
# that run, so a change made from now on is confirmed on another fresh seed, never on it.
# 7331: also run once that day on the same code (its day query failed: an aliased
# start; results/accuracy_urban_s7331.json), diagnosed after it: spent too; 4099's
# results are in results/accuracy_urban_s4099.json. The ORB grid (ad96155) was chosen on
# 4099 and 7331, then 5501 was run once on that commit (results/accuracy_urban_s5501.json,
# --no-stereo), untouched before; then 6607 the same way on the same product code
# (results/accuracy_urban_s6607.json). The mode's Gaussian filter (2d056ef): 8123, run
# once (results/accuracy_urban_s8123.json; its late start led to the two FAST
# thresholds); 9377 on 3852c48 (results/accuracy_urban_s9377.json); 2719 on the FAST
# count rule with a low threshold of 7 (results/accuracy_urban_s2719.json); 3583 on the
# low threshold of 12 (results/accuracy_urban_s3583.json). 2026-11-29: 4470 on the
# refinement's yaw-rate bias and far-hypothesis gate (results/accuracy_urban_s4470.json;
# two of its filter seeds led to the restart on disagreement), 5219 on that restart
# (results/accuracy_urban_s5219.json), 6343 on the joint pose's best start and a filter
# start from the hypotheses' Gaussians (results/accuracy_urban_s6343.json; its night
# failed on the start, taken out), 7702 on fe0ccb8 (results/accuracy_urban_s7702.json),
# 8861 on the lost signal under the broader component (results/accuracy_urban_s8861.json).
# Then the night condition's calibration (9639299): 9154, run once (results/
# accuracy_urban_s9154.json), 2468 on the same code (results/accuracy_urban_s2468.json) and
# 5807 on f2f78e2 (results/accuracy_urban_s5807.json); 3197 on 08f5f2f found a query
# driving 100 m past its map's end and the filter taken 157 m away by an aliased street
# after the silence (results/accuracy_urban_s3197.json); with both fixed (1bf4bf7: the
# re-seed's drift bound, capped query runs cut to the map's stretch), 6121, run once
# (results/accuracy_urban_s6121.json), and 7413 on the same code (results/
# accuracy_urban_s7413.json). With a re-seed's support only from frames nearer the
# candidate than the filter (dabbabe): 8317, run once (results/accuracy_urban_s8317.json),
# and 2905 on the same code (results/accuracy_urban_s2905.json). With the refinement
# waiting out a short disagreement with the particles (f3e2a5e): 4721, run once
# (results/accuracy_urban.json), 6529 and 1907 on the same code (results/
# accuracy_urban_s6529.json, accuracy_urban_s1907.json), 3361 on its warm-up fix (results/
# accuracy_urban_s3361.json).
# Changes from then on need another fresh seed.
HELD_OUT_SEED = 4721
URBAN_VARIANTS = (
    "full",
    "full_mode",
    "kidnapped",
    "no_prior",
    "top1",
    "topk_mean",
    "best_pnp",
)


def limit_threads() -> None:
    import cv2
    import faiss
    from threadpoolctl import threadpool_limits

    cv2.setNumThreads(1)
    faiss.omp_set_num_threads(1)
    threadpool_limits(1)


def add_city_arguments(parser) -> None:
    """--size, --frames, --seed (the held-out one by default), --data and --root: the urban
    city a measuring bench runs on (:func:`city_root`)."""
    parser.add_argument("--size", default="medium")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--seed", type=int, default=HELD_OUT_SEED)
    parser.add_argument("--data", type=Path, default=Path(__file__).parent / "data")
    parser.add_argument(
        "--root", type=Path, default=None, help="an existing dataset (its size, frames, seed given)"
    )


def city_root(args) -> Path:
    """The dataset folder of :func:`add_city_arguments`' arguments."""
    return args.root or args.data / f"urban_{args.size}_{args.frames}_s{args.seed}"


def ensure_dataset(
    root: Path,
    size: str,
    frames: int,
    seed: int,
    runs: tuple[str, ...],
    scenario: str = "urban",
    exact: bool = False,
):
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.recording import RecordingErrors

    if (root / "dataset.json").exists():
        return json.loads((root / "dataset.json").read_text())
    print(
        f"generating a {size} {scenario} world into {root} ({frames} frames per run) ...",
        flush=True,
    )
    t0 = time.time()
    generate_dataset(
        GenerateConfig(
            scenario=scenario,
            size=size,
            seed=seed,
            runs=runs,
            max_frames=frames,
            workers=2,
            errors=RecordingErrors.none() if exact else RecordingErrors(),
        ),
        root,
    )
    print(f"  done in {time.time() - t0:.0f} s", flush=True)
    return json.loads((root / "dataset.json").read_text())


def calibrate_on(train, vocabulary, trainnight=None, covariance: str = "pnp"):
    """The measurement model fitted on a training run (KittiSequence / TumRun), each frame
    read once, exactly as the server's calibration job does; with ``trainnight``, on the
    pooled samples of both runs (each against its own temporary map). ``covariance``
    selects the model the result uses ("pnp", the server's default, "paper" or "quality";
    all are fitted)."""
    from monoloc.server.calibrate import CalibrationConfig, TrainingRun, calibrate_runs
    from monoloc.server.jobs.calibration import training_frames

    named = [("train", train)] + ([("trainnight", trainnight)] if trainnight else [])
    runs = [TrainingRun(training_frames(seq), name, seq.n_frames) for name, seq in named]
    return calibrate_runs(
        runs,
        train.intrinsics,
        vocabulary,
        CalibrationConfig(covariance=covariance),
        np.random.default_rng(0),
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
    parser.add_argument("--scenario", default="urban", choices=("urban", "indoor", "fleet"))
    parser.add_argument(
        "--fleet-camera", default="issue48", help="--scenario fleet: a FLEET_CAMERAS preset"
    )
    parser.add_argument("--size", default="medium")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--seed", type=int, default=HELD_OUT_SEED)
    parser.add_argument("--data", type=Path, default=Path(__file__).parent / "data")
    parser.add_argument(
        "--no-floor", action="store_true", help="skip the error floor (recording errors off)"
    )
    parser.add_argument(
        "--filter-seeds",
        type=int,
        default=3,
        help="the day query and the night with night entries also with filter seeds "
        "1..N-1: the night/day goal is judged on the mean over the seeds",
    )
    parser.add_argument(
        "--no-stereo",
        action="store_true",
        help="skip the stereo-built map vs the LiDAR-built map (bench/stereo.py)",
    )
    args = parser.parse_args()
    limit_threads()
    if args.scenario == "indoor":
        return main_indoor(args)
    if args.scenario == "fleet":
        from bench import fleet_camera

        return fleet_camera.main(args)
    root = args.data / f"urban_{args.size}_{args.frames}_s{args.seed}"
    runs = ("map", "query", "train", "night", "nightmap", "trainnight")
    meta = ensure_dataset(root, args.size, args.frames, args.seed, runs)
    night_train = night_training_run(root, meta, args)
    true_world = true_poses(meta, args)
    out = {"scenario": "urban", "size": args.size, "seed": args.seed}
    out["frames_per_run"] = args.frames
    out.update(
        urban_city(
            root,
            meta,
            night=True,
            night_train=night_train,
            true_world=true_world,
            filter_seeds=args.filter_seeds,
        )
    )
    if not args.no_floor:
        exact_root = root.with_name(root.name + "_exact")
        exact_meta = ensure_dataset(
            exact_root, args.size, args.frames, args.seed, runs[:3], exact=True
        )
        print("\nerror floor: the same pipeline on the same city with the recording errors off")
        floor = urban_city(
            exact_root,
            exact_meta,
            night=False,
            variants=("full", "best_pnp"),
        )
        out["floor"] = floor
    if not args.no_stereo:
        from bench import stereo

        stereo_root = root.with_name(root.name + "_stereo")
        stereo_meta = stereo.ensure_stereo_dataset(stereo_root, args.size, args.frames, args.seed)
        print("\nmaps from a stereo camera: same map, train and query runs, LiDAR beside stereo")
        out["stereo"] = stereo.compare(stereo_root, stereo_meta)
    print_goals(out)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "accuracy_urban.json").write_text(json.dumps(out, indent=2) + "\n")


def registered_night(root, meta, vocab, night_seq, nsig, model, lever):
    """The night query against the day map + the night run registered to it first (as
    ``monoloc map ingest --register`` / ``register_to_map`` does): (metrics row, the
    registration's summary)."""
    from bench.lab.evaluation import MemoryMap, evaluate_run, metrics_row
    from monoloc.core.registration import RegistrationConfig
    from monoloc.server.ingest.sources import read_kitti_sequence

    memory = MemoryMap.empty(vocab)
    memory.add_run(read_kitti_sequence(root, sequence_of(meta, "map")))
    nightmap = read_kitti_sequence(root, sequence_of(meta, "nightmap"))
    memory.add_run(nightmap, tags=("night",), register=RegistrationConfig())
    summary = memory.corrections[-1].summary()
    print(f"night run registered to the day map: {summary}")
    result = evaluate_run(memory, night_seq, nsig, model, lever_arm_m=lever, variants=("full",))
    return metrics_row(result.metrics["full"]), summary


def night_training_run(root: Path, meta: dict, args) -> tuple[Path, str]:
    """(dataset root, sequence id) of the `trainnight` run: in the dataset itself, or, for
    a dataset generated without it (cached before the run existed), in a sibling dataset
    of that run alone (the same route through the training district; the cached dataset
    is left as it is)."""
    seq = sequence_of(meta, "trainnight")
    if seq is not None:
        return root, seq
    extra = root.with_name(root.name + "_trainnight")
    extra_meta = ensure_dataset(extra, args.size, args.frames, args.seed, ("trainnight",))
    return extra, sequence_of(extra_meta, "trainnight")


def true_poses(meta: dict, args) -> dict[str, np.ndarray]:
    """The sim's true planar camera poses (N, 3) per run of the dataset, in its z-up world."""
    from monoloc.sim.generate import GenerateConfig
    from monoloc.sim.urban.truth import true_planar_poses

    runs = tuple(seq["run"] for seq in meta["sequences"])
    config = GenerateConfig(
        scenario="urban", size=args.size, seed=args.seed, runs=runs, max_frames=args.frames
    )
    true = true_planar_poses(config, np.array(meta["T_simworld_from_zupworld"]))
    stale = [
        f"{seq['run']} {seq['frames']} frames on disk, {len(true[seq['run']])} planned"
        for seq in meta["sequences"]
        if len(true[seq["run"]]) != seq["frames"]
    ]
    if stale:
        raise SystemExit(
            f"the dataset was generated by another version of the sim ({'; '.join(stale)}): "
            "delete its folder to generate it again"
        )
    return true


def written_poses(root: Path, seq_id: str) -> np.ndarray:
    from monoloc.core.geometry import planar_from_T_world_from_cam
    from monoloc.server.ingest.sources import read_kitti_sequence

    seq = read_kitti_sequence(root, seq_id)
    return np.array([planar_from_T_world_from_cam(f.T_world_from_cam) for f in seq.frames])


# noise (m, per axis) added to every hypothesis to test the best-of-k oracle with
BLUR_SIGMAS_M = (0.01, 0.02, 0.04)


def recording_floor(
    result, variant: str, placed_world: np.ndarray, query_true_world: np.ndarray
) -> dict:
    """What the recording errors alone cost, and the filter judged without them.

    ``placed_world`` (N, 3): where a localizer exact relative to the map puts each frame
    (``truth_in_map_frame``). floor: its error against the written truth (what the
    figures are judged by); ``query_alone``: the query's written truth against its true
    poses (``query_true_world`` (N, 3)), what even an exact map and an exact localizer
    would score; ``exact_over_best_of_k``: the filter / best-of-k goal's ratio for the
    exact-to-map localizer (median of floor over the median best of k, against the written
    truth, on the frames with hypotheses). The filter, the best of k and the likeliest
    hypothesis (the per-frame estimator a filter must beat: no oracle) against
    ``placed_world``: their own error, without the map's and the query's recording
    errors. ``best_of_k_blurred``: the best of k against the written truth after every
    hypothesis is moved by isotropic Gaussian noise of each ``BLUR_SIGMAS_M`` (a fixed
    generator), median on the same frames: where it falls below the plain best of k, the
    oracle is rewarded for spread, not for information a filter could use."""
    from monoloc.client.trajectory import best_of_k_errors, blurred_best_of_k_errors

    truth = result.truth_world
    floor = np.linalg.norm(placed_world[:, :2] - truth[:, :2], axis=1)
    alone = np.linalg.norm(np.asarray(query_true_world)[:, :2] - truth[:, :2], axis=1)
    est = result.estimates[variant]
    own = np.linalg.norm(est[:, :2] - placed_world[:, :2], axis=1)
    best_k = best_of_k_errors(result.hypotheses_world, placed_world)
    best_k_written = best_of_k_errors(result.hypotheses_world, truth)
    likeliest = np.linalg.norm(result.likeliest_world[:, :2] - placed_world[:, :2], axis=1)
    ok = np.isfinite(best_k) & np.isfinite(own)

    def stats(e):
        e = e[np.isfinite(e)]
        return {"median_m": float(np.median(e)), "rmse_m": float(np.sqrt(np.mean(e**2)))}

    rng = np.random.default_rng(0)
    blurred = {
        f"{sigma:.3f}": float(
            np.median(blurred_best_of_k_errors(result.hypotheses_world, truth, sigma, rng)[ok])
        )
        for sigma in BLUR_SIGMAS_M
    }
    return {
        "floor": stats(floor),
        "best_of_k_written_median_m": float(np.median(best_k_written[ok])),
        "best_of_k_blurred": blurred,
        "query_alone": stats(alone),
        "exact_over_best_of_k": float(np.median(floor[ok]) / np.median(best_k_written[ok])),
        "filter_vs_map_frame": stats(own),
        "best_of_k_vs_map_frame_median_m": float(np.median(best_k[ok])),
        "filter_vs_map_frame_median_on_frames_with_hypotheses_m": float(np.median(own[ok])),
        "likeliest_vs_map_frame_median_m": float(np.median(likeliest[ok & np.isfinite(likeliest)])),
    }


def print_floor(name: str, f: dict) -> None:
    ratio = f["filter_vs_map_frame_median_on_frames_with_hypotheses_m"] / max(
        f["best_of_k_vs_map_frame_median_m"], 1e-9
    )
    print(
        f"{name}: a pose exact relative to the map scores median {f['floor']['median_m']:.3f} m"
        f" / RMSE {f['floor']['rmse_m']:.3f} m against the written truth (the recording "
        f"errors' floor; filter / best of k {f['exact_over_best_of_k']:.2f}); the query's "
        f"written truth alone is off its true poses by median "
        f"{f['query_alone']['median_m']:.3f} m / RMSE {f['query_alone']['rmse_m']:.3f} m; "
        f"against the map's own frame the filter has median "
        f"{f['filter_vs_map_frame']['median_m']:.3f} m / RMSE "
        f"{f['filter_vs_map_frame']['rmse_m']:.3f} m, best of k median "
        f"{f['best_of_k_vs_map_frame_median_m']:.3f} m (filter / best of k {ratio:.2f})"
        + (
            f", the likeliest hypothesis median {f['likeliest_vs_map_frame_median_m']:.3f} m"
            if "likeliest_vs_map_frame_median_m" in f  # results before 2026-11-29 lack it
            else ""
        )
    )
    if "best_of_k_blurred" in f:  # results before 2026-11-29 evening lack it
        blurred = ", ".join(
            f"{float(sigma) * 100:.0f} cm: {m:.3f} m" for sigma, m in f["best_of_k_blurred"].items()
        )
        print(
            f"  the best of k against the written truth, median "
            f"{f['best_of_k_written_median_m']:.3f} m; with every hypothesis blurred by "
            f"random noise ({blurred}): lower means the oracle gains from spread alone"
        )


PAPER_MODEL = "paper model"
NO_TAIL = "paper model without the tail"
NO_ALT = "PnP covariance model without the alternative poses"
DAY_ONLY = "the day calibration alone (no night condition)"


def urban_city(
    root: Path,
    meta: dict,
    night: bool,
    variants=URBAN_VARIANTS,
    night_train: tuple[Path, str] | None = None,
    true_world: dict[str, np.ndarray] | None = None,
    filter_seeds: int = 1,
) -> dict:
    """Calibrate on `train`, map the `map` run, evaluate the `query` run with each variant
    (and the night runs); print the tables; the figures as a dict.

    The model is the server's default ("pnp", with the alternative poses), calibrated on
    `train`; the paper's covariance and "pnp" without the alternative poses run beside
    it on the day query and the night with night entries. With ``night_train`` (root, sequence
    of the `trainnight` run), the model has a "night" condition calibrated on it alone
    (``MeasurementModel.conditions``: it weighs the hypotheses of the entries tagged night);
    the day calibration alone runs beside it on the night with night entries. (Until
    2026-11-29 the quality-aware model calibrated on `train` + `trainnight` pooled ran
    there instead: it made night better on development cities 41 and 42 but worse on a
    held-out city.)
    With ``true_world``
    (the sim's true poses per run), the recording errors' floor (:func:`recording_floor`).
    With ``filter_seeds`` N > 1, the day query ("full") and the night with night entries
    run again with the filter seeds 1..N-1 (``EvalConfig.seed``; the RANSAC draws follow
    it): a night's RMSE turns on a few stretches and moves a lot from seed to seed."""
    from bench.lab.evaluation import (
        EvalConfig,
        MemoryMap,
        evaluate_run,
        metrics_row,
        stage_percentiles,
    )
    from monoloc.client.replay import read_kitti_run, rig_lever_arm_m
    from monoloc.client.trajectory import ExcursionCauses
    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.server.localize import LocalizeConfig, PoseConfig
    from monoloc.server.vision.vocabulary import load_default_vocabulary

    vocab = load_default_vocabulary()
    # the pipeline without the alternative pose (an ablation)
    without_alternative = EvalConfig(localize=LocalizeConfig(poses=PoseConfig(alternative=None)))
    train_id = sequence_of(meta, "train")
    lever = fitted_lever_arm_m(read_kitti_run(root, train_id), rig_lever_arm_m(root))
    t0 = time.time()
    train = read_kitti_sequence(root, train_id)
    paper_calib = calibrate_on(train, vocab)
    print(f"calibrated on {paper_calib.provenance['used']} hypotheses in {time.time() - t0:.0f} s")
    calib, night_calib = paper_calib, None
    model = calib.model
    if night_train is not None:
        # the night condition's own calibration (a night training run against its own
        # night map), as an operator calibrates with condition=night: it weighs the
        # hypotheses of entries tagged night; the day query has none, so it runs as before
        t0 = time.time()
        night_calib = calibrate_on(read_kitti_sequence(*night_train), vocab)
        model = model.with_condition("night", night_calib.model)
        print(
            f"calibrated the night condition on trainnight: {night_calib.provenance['used']} "
            f"hypotheses in {time.time() - t0:.0f} s"
        )
    memory = MemoryMap.empty(vocab)
    t0 = time.time()
    memory.add_run(read_kitti_sequence(root, sequence_of(meta, "map")))
    print(f"map: {len(memory.refs)} entries in {time.time() - t0:.0f} s")
    query_id = sequence_of(meta, "query")
    query = read_kitti_sequence(root, query_id)
    signals = read_kitti_run(root, query_id).signals
    result = evaluate_run(memory, query, signals, model, lever_arm_m=lever, variants=variants)
    rows = [(v, metrics_row(m)) for v, m in result.metrics.items()]
    # beside the default (the "pnp" model, alternative poses): the paper's covariance
    # (Sigma1 for every hypothesis, with and without monoloc's tail) and "pnp" without the
    # alternative poses, each on the pipeline without them; the quality-aware model
    paper_model = model.with_covariance("paper")
    arms = [
        (PAPER_MODEL, paper_model, without_alternative),
        (NO_TAIL, without_tail(paper_model), without_alternative),
        (NO_ALT, model, without_alternative),
    ]
    arm_runs = {}
    for label, arm_model, arm_config in arms:
        arm_runs[label] = evaluate_run(
            memory, query, signals, arm_model, arm_config, lever, variants=("full",)
        )
        rows.append((f"full, {label}", metrics_row(arm_runs[label].metrics["full"])))
    out = {
        "calibration": {"model": model.to_dict(), "provenance": calib.provenance},
        "calibration_night": None
        if night_calib is None
        else {"model": night_calib.model.to_dict(), "provenance": night_calib.provenance},
        "query": dict(rows),
        "stages_ms": stage_percentiles(result.timings_ms),
        "paper": PAPER,
        "goals": GOALS,
        "reseeds": result.reseeds,
        "lever_arm_m": {"fitted_on_train": lever, "rig": rig_lever_arm_m(root)},
        "bias": bias_report(result, [v for v in ("full", "full_mode") if v in variants]),
    }
    if "kidnapped" in result.estimates:
        out["kidnapped_recover_s"] = recovery_s(result, "kidnapped")
    out["excursions"] = {"query": excursions(result, "full")}
    by_seed = {"day_rmse_m": [result.metrics["full"].position_rmse_m], "night_rmse_m": []}
    for seed in range(1, filter_seeds if night else 1):
        again = evaluate_run(
            memory, query, signals, model, EvalConfig(seed=seed), lever, variants=("full",)
        )
        by_seed["day_rmse_m"].append(again.metrics["full"].position_rmse_m)
    map_id = sequence_of(meta, "map")
    if true_world is not None:
        from monoloc.client.trajectory import truth_in_map_frame

        map_true, map_written = true_world["map"], written_poses(root, map_id)
        placed = truth_in_map_frame(true_world["query"], map_true, map_written)
        out["recording_floor"] = recording_floor(result, "full", placed, true_world["query"])
        if "full_mode" in result.estimates:
            out["recording_floor_mode"] = recording_floor(
                result, "full_mode", placed, true_world["query"]
            )
        out["recording_floor_paper"] = recording_floor(
            arm_runs[PAPER_MODEL], "full", placed, true_world["query"]
        )
    night_rows = []
    night_id, nightmap_id = sequence_of(meta, "night"), sequence_of(meta, "nightmap")
    if night and night_id:
        night_seq = read_kitti_sequence(root, night_id)
        nsig = read_kitti_run(root, night_id).signals
        before = evaluate_run(memory, night_seq, nsig, model, lever_arm_m=lever, variants=("full",))
        night_rows.append(("night, day map", metrics_row(before.metrics["full"])))
        if nightmap_id:
            added = memory.add_run(read_kitti_sequence(root, nightmap_id), tags=("night",))
            after = evaluate_run(
                memory, night_seq, nsig, model, lever_arm_m=lever, variants=("full", "full_mode")
            )
            night_rows.append(("night, + night entries", metrics_row(after.metrics["full"])))
            night_rows.append(
                (
                    "night, + night entries, the particles' mode",
                    metrics_row(after.metrics["full_mode"]),
                )
            )
            by_seed["night_rmse_m"].append(after.metrics["full"].position_rmse_m)
            for seed in range(1, filter_seeds):
                again = evaluate_run(
                    memory, night_seq, nsig, model, EvalConfig(seed=seed), lever, ("full",)
                )
                by_seed["night_rmse_m"].append(again.metrics["full"].position_rmse_m)
            night_arms = list(arms)
            if night_calib is not None:
                night_arms.append((DAY_ONLY, calib.model, EvalConfig()))
            for label, arm_model, arm_config in night_arms:
                arm = evaluate_run(
                    memory, night_seq, nsig, arm_model, arm_config, lever, variants=("full",)
                )
                night_rows.append(
                    (f"night, + night entries, {label}", metrics_row(arm.metrics["full"]))
                )
            registered, correction = registered_night(
                root, meta, vocab, night_seq, nsig, model, lever
            )
            night_rows.append(("night, + night entries registered to the map", registered))
            out["night_registration"] = correction
            out["night_entries_added"] = added
            out["night_bias"] = bias_report(after, ["full", "full_mode"])
            out["excursions"]["night, + night entries"] = excursions(after, "full")
            if true_world is not None:
                placed = truth_in_map_frame(
                    true_world["night"],
                    np.concatenate([map_true, true_world["nightmap"]]),
                    np.concatenate([map_written, written_poses(root, nightmap_id)]),
                )
                # two maps (day and night entries) with independent recording errors:
                # the nearest entry of either stands for the map, a rougher placement
                out["night_recording_floor"] = recording_floor(
                    after, "full", placed, true_world["night"]
                )
    out["night"] = dict(night_rows)
    if len(by_seed["day_rmse_m"]) > 1 and len(by_seed["night_rmse_m"]) > 1:
        out["filter_seeds"] = by_seed
        day = " / ".join(f"{v:.3f}" for v in by_seed["day_rmse_m"])
        night_rmse = " / ".join(f"{v:.3f}" for v in by_seed["night_rmse_m"])
        print(
            f"filter seeds 0-{len(by_seed['day_rmse_m']) - 1}: day RMSE {day} m, "
            f"night with night entries {night_rmse} m"
        )
    print_table(rows + night_rows)
    print_bias(out["bias"])
    if "recording_floor" in out:
        print()
        print_floor("query", out["recording_floor"])
    if "recording_floor_mode" in out:
        print_floor("query, the particles' mode", out["recording_floor_mode"])
    if "recording_floor_paper" in out:
        print_floor(f"query, {PAPER_MODEL}", out["recording_floor_paper"])
    if "night_recording_floor" in out:
        print_floor(
            "night, + night entries (day and night entries: approximate)",
            out["night_recording_floor"],
        )
    for run, causes in out["excursions"].items():
        print(f"{run}: {ExcursionCauses(**causes).text()}")
    if "kidnapped_recover_s" in out:
        print(
            f"kidnapped start ({EvalConfig().kidnap_offset_m:g} m to the side): back within 0.25 m "
            f"for good after {out['kidnapped_recover_s']:.1f} s; re-seeds {result.reseeds}"
        )
    return out


def without_tail(model):
    """``model`` (and its conditions' models) with the paper covariance's tail off."""
    return dataclasses.replace(
        model,
        tail_weight=0.0,
        conditions={
            name: dataclasses.replace(m, tail_weight=0.0) for name, m in model.conditions.items()
        },
    )


def fitted_lever_arm_m(train_run, rig_m: float | None) -> float:
    """The lever arm fitted on the training run's poses and speeds, as a deployment on
    data without a rig description would (printed beside the sim rig's true value)."""
    from monoloc.client.motion import fit_lever_arm_m

    fitted = fit_lever_arm_m(train_run.truth_world, train_run.timestamps_s, train_run.signals[:, 0])
    rig = "-" if rig_m is None else f"{rig_m:.3f}"
    print(f"camera lever arm fitted on the train run: {fitted:.3f} m (sim rig: {rig} m)")
    return fitted


def excursions(result, variant: str) -> dict:
    """The frames beyond 0.25 m of the written truth, by what their hypotheses held."""
    from monoloc.client.trajectory import excursion_causes

    causes = excursion_causes(
        result.estimates[variant], result.truth_world, result.hypotheses_world, 0.25
    )
    return causes.to_dict()


def recovery_s(result, variant: str) -> float | None:
    from monoloc.client.trajectory import time_to_recover

    est, truth = result.estimates[variant], result.truth_world
    err = np.linalg.norm(est[:, :2] - truth[:, :2], axis=1)
    s = time_to_recover(err, result.timestamps_s, 0, tolerance_m=0.25)
    return s if np.isfinite(s) else None


def bias_report(result, variants: list[str]) -> dict:
    """Along/cross-track and heading by turning class for the filter variants and for the
    server's own likeliest hypothesis per frame; best-of-k and likeliest beside the
    filter's median and mean error."""
    from monoloc.client.trajectory import best_of_k_errors, errors_by_turning

    truth, times = result.truth_world, result.timestamps_s
    sources = {v: result.estimates[v] for v in variants}
    sources["likeliest hypothesis"] = result.likeliest_world
    by_class = {
        name: {k: v.to_dict() for k, v in errors_by_turning(est, truth, times).items()}
        for name, est in sources.items()
    }
    best_k = best_of_k_errors(result.hypotheses_world, truth)
    with_hyp = np.isfinite(best_k)

    def err(est):
        return np.linalg.norm(est[:, :2] - truth[:, :2], axis=1)

    likeliest = err(result.likeliest_world)
    frames = {
        "frames_with_hypotheses": float(np.mean(with_hyp)),
        "best_of_k_median_m": float(np.median(best_k[with_hyp])) if with_hyp.any() else None,
        "likeliest_median_m": float(np.median(likeliest[with_hyp])) if with_hyp.any() else None,
        "likeliest_mean_m": float(np.mean(likeliest[with_hyp])) if with_hyp.any() else None,
    }
    for v in variants:
        e = err(result.estimates[v])
        ok = with_hyp & np.isfinite(e)
        frames[f"{v}_median_m"] = float(np.median(e[ok])) if ok.any() else None
        frames[f"{v}_mean_m"] = float(np.mean(e[ok])) if ok.any() else None
    return {"by_class": by_class, "frames_with_hypotheses": frames}


def print_bias(bias: dict) -> None:
    print(
        f"\n{'errors by turning class':<24}{'class':>9}{'frames':>7}{'along m':>9}"
        f"{'cross m':>9}{'inward m':>9}{'head deg':>9}{'ahead deg':>10}{'head rmse':>10}"
    )
    for name, classes in bias["by_class"].items():
        for cls, e in classes.items():
            print(
                f"{name:<24}{cls:>9}{e['n_frames']:>7}{e['along_mean_m']:>+9.3f}"
                f"{e['cross_mean_m']:>+9.3f}{e['cross_inward_mean_m']:>+9.3f}"
                f"{e['heading_mean_deg']:>+9.2f}{e['heading_ahead_mean_deg']:>+10.2f}"
                f"{e['heading_rmse_deg']:>10.2f}"
            )
    f = bias["frames_with_hypotheses"]

    def g(x):
        return "-" if x is None else f"{x:.3f}"

    print(
        f"on the {100 * f['frames_with_hypotheses']:.0f} % of frames with hypotheses: "
        f"best of k median {g(f['best_of_k_median_m'])} m, likeliest hypothesis median "
        f"{g(f['likeliest_median_m'])} m / mean {g(f['likeliest_mean_m'])} m"
    )
    for key in f:
        if key.endswith("_median_m") and key not in ("best_of_k_median_m", "likeliest_median_m"):
            v = key.removesuffix("_median_m")
            print(f"  filter ({v}): median {g(f[key])} m / mean {g(f[v + '_mean_m'])} m")


def print_goals(out: dict) -> None:
    """Each goal of issue 13 item 5 beside the measured figure."""
    full = out["query"]["full"]
    frames = out["bias"]["frames_with_hypotheses"]
    night = out.get("night", {})
    rows = [
        ("position RMSE (m)", full["position_rmse_m"], "<=", GOALS["position_rmse_m"]),
        ("position median (m)", full["position_median_m"], "<=", GOALS["position_median_m"]),
        ("heading RMSE (deg)", full["heading_rmse_deg"], "<=", GOALS["heading_rmse_deg"]),
        ("within 0.25 m / 2 deg", full["within_0_25m_2deg"], ">=", GOALS["within_0_25m_2deg"]),
    ]
    if frames["best_of_k_median_m"] and frames.get("full_median_m") is not None:
        ratio = frames["full_median_m"] / frames["best_of_k_median_m"]
        rows.append(
            ("filter / best-of-k median", ratio, "<=", GOALS["filter_median_over_best_of_k"])
        )
    if "night, + night entries" in night and full["position_rmse_m"]:
        n_rmse = night["night, + night entries"]["position_rmse_m"]
        if n_rmse is not None:
            rows.append(
                (
                    "night (+night) / day RMSE",
                    n_rmse / full["position_rmse_m"],
                    "<=",
                    GOALS["night_rmse_over_day"],
                )
            )
        seeds = out.get("filter_seeds")
        if seeds:
            rows.append(
                (
                    f"night / day, filter seeds 0-{len(seeds['day_rmse_m']) - 1} mean",
                    float(np.mean(seeds["night_rmse_m"]) / np.mean(seeds["day_rmse_m"])),
                    "<=",
                    GOALS["night_rmse_over_day"],
                )
            )
        # Better with the night images than without: the share of all frames within
        # 0.25 m / 2 deg (a frame without an estimate is not within). An RMSE ratio would
        # compare different frames: the day map alone often localizes a few frames only.
        before = night.get("night, day map", {}).get("within_0_25m_2deg")
        after = night["night, + night entries"].get("within_0_25m_2deg")
        if before is not None and after is not None:
            rows.append(("night +night - day map, within share", after - before, ">=", 0.0))
    # what a pose exact relative to the map scores on the same figure (recording_floor):
    # a "<=" goal under it cannot be met against this city's written truth
    floors = {}
    if "recording_floor" in out:
        rf = out["recording_floor"]
        floors = {
            "position RMSE (m)": rf["floor"]["rmse_m"],
            "position median (m)": rf["floor"]["median_m"],
            "filter / best-of-k median": rf["exact_over_best_of_k"],
        }
    print(f"\nseed {out['seed']}: goals of issue 13 item 5 (medium city, recording errors on)")
    print(f"{'figure':<38}{'measured':>10}{'goal':>12}{'floor':>8}  met")
    for name, value, op, goal in rows:
        met = value <= goal if op == "<=" else value >= goal
        floor = floors.get(name)
        verdict = "yes" if met else "NO"
        if not met and floor is not None and goal < floor:
            verdict += " (the goal is under the floor)"
        print(
            f"{name:<38}{value:>10.3f}{op + ' ' + format(goal, 'g'):>12}"
            f"{'-' if floor is None else format(floor, '.3f'):>8}  {verdict}"
        )
    if "floor" in out:
        fl = out["floor"]["query"]["full"]
        print(
            f"error floor (recording errors off): RMSE {fl['position_rmse_m']:.3f} m, median "
            f"{fl['position_median_m']:.3f} m, heading RMSE {fl['heading_rmse_deg']:.2f} deg, "
            f"{100 * fl['within_0_25m_2deg']:.1f} % within 0.25 m / 2 deg"
        )
    if "recording_floor" in out:
        rf = out["recording_floor"]
        print(
            f"recording errors' floor (a pose exact relative to the map, judged against the "
            f"written truth): median {rf['floor']['median_m']:.3f} m, RMSE "
            f"{rf['floor']['rmse_m']:.3f} m, filter / best of k "
            f"{rf['exact_over_best_of_k']:.2f}; the query's written truth alone against its "
            f"true poses: median {rf['query_alone']['median_m']:.3f} m; the filter against "
            f"the map's own frame: median "
            f"{rf['filter_vs_map_frame']['median_m']:.3f} m, RMSE "
            f"{rf['filter_vs_map_frame']['rmse_m']:.3f} m"
        )
    out["goals_met"] = {
        name: (value <= goal if op == "<=" else value >= goal) for name, value, op, goal in rows
    }
    out["goals_floor"] = floors


PAPER_INDOOR = {"open_loop_within_0_1m": 1.0, "open_loop_within_0_06m": 0.92}


def main_indoor(args) -> None:
    from bench.lab.evaluation import (
        EvalConfig,
        MemoryMap,
        evaluate_run,
        metrics_row,
        stage_percentiles,
    )
    from monoloc.client.replay import read_tum_run as read_tum_replay
    from monoloc.client.replay import rig_lever_arm_m
    from monoloc.server.ingest.sources import read_tum_run
    from monoloc.server.localize import LocalizeConfig, PoseConfig
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
    lever = fitted_lever_arm_m(read_tum_replay(root / "train"), rig_lever_arm_m(root / "map"))
    train = read_tum_run(root / "train")
    calib = calibrate_on(train, vocab)
    memory = MemoryMap.empty(vocab)
    memory.add_run(read_tum_run(root / "map"))
    query = read_tum_run(root / "query")
    signals = read_tum_replay(root / "query").signals
    variants = ("full", "full_mode", "no_prior", "top1", "topk_mean", "best_pnp")
    base = evaluate_run(memory, query, signals, calib.model, lever_arm_m=lever, variants=variants)
    rows = [(v, metrics_row(m)) for v, m in base.metrics.items()]
    quality = evaluate_run(
        memory,
        query,
        signals,
        calib.model.with_covariance("quality"),
        lever_arm_m=lever,
        variants=("full",),
    )
    rows.append(("full, quality-aware model", metrics_row(quality.metrics["full"])))
    paper = evaluate_run(
        memory,
        query,
        signals,
        calib.model.with_covariance("paper"),
        EvalConfig(localize=LocalizeConfig(poses=PoseConfig(alternative=None))),
        lever,
        variants=("full",),
    )
    rows.append((f"full, {PAPER_MODEL}", metrics_row(paper.metrics["full"])))
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
                "seed": args.seed,
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

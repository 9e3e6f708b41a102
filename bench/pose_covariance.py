"""What the PnP pose covariance says about a hypothesis's error, beside the inlier count
and the reprojection error (the quality-aware model's features).

For every frame of the day query (against the map's entries) and of the night query
(against the map plus the night entries) of an urban sim city (the held-out one by
default, generated if missing), one search of the whole map: each per-entry hypothesis
carries the planar covariance of its pose from its own inliers at 1 px
(``vision.pose_covariance``). Its error is taken against its entry's own frame: the
query's true pose moved by the recording error (written minus true) of the map frame
the entry was built from, so the recording errors between the runs do not mask what the
hypothesis itself got wrong.

Prints, per run: Spearman rank correlation of the position error with the position
spread sqrt(var X + var Y), with 1 / sqrt(inliers) and with the mean reprojection error;
quartiles of the error and of the spread; the share of hypotheses more than 0.3 m off
among the half with the smaller spread and the half with the larger one; and the pixel
noise that would make the spread the error's size (median of error / spread). Measures
only: nothing in monoloc's defaults is chosen from it. Writes
bench/results/pose_covariance.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from bench.accuracy import (
    add_city_arguments,
    city_root,
    ensure_dataset,
    limit_threads,
    sequence_of,
    true_poses,
    written_poses,
)

OFF_M = 0.3


def measure(memory, query, intrinsics, query_true, map_written, map_true, seed: int, scales: bool):
    """(H, 4): per per-entry hypothesis, position error (m) against the query's true pose
    ``query_true`` (N, 3) moved by the recording error of the entry's own map frame (the
    frame of ``map_written`` (M, 3) at the entry's pose; ``map_true`` (M, 3) its true
    pose), position spread at 1 px (m; the inliers weighed by their keypoints' pyramid
    scales with ``scales``), inliers, mean reprojection error (px)."""
    from monoloc.server.localize import FrameStages, LocalizeConfig, pose_hypotheses
    from monoloc.server.localize.in_process import InProcessLocalizer
    from monoloc.server.vision.pose_covariance import position_spread_m

    def unweighted(keypoints_px, refs, matches, e_vlad, intrinsics, config, rng, prior=None,
                   keypoint_scales=None, descriptors=None):  # fmt: skip
        """The pose stage with every inlier at full resolution in the covariance."""
        return pose_hypotheses(
            keypoints_px, refs, matches, e_vlad, intrinsics, config, rng, prior, None,
            descriptors,
        )  # fmt: skip

    localizer = InProcessLocalizer(
        memory.index,
        memory.lookup,
        memory.vocabulary,
        intrinsics,
        np.random.default_rng(seed),
        LocalizeConfig(),
        FrameStages() if scales else FrameStages(poses=unweighted),
    )
    recording_error = map_written[:, :2] - map_true[:, :2]
    rows = []
    for i, frame in enumerate(query.frames):
        result = localizer.localize(query.load(frame).image_gray).result
        for h in result.hypotheses:
            if h.joint or h.covariance_px1 is None:
                continue
            own = int(np.argmin(np.hypot(*(map_written[:, :2] - h.entry_pose_world[:2]).T)))
            placed = query_true[i, :2] + recording_error[own]
            error = float(np.hypot(*(h.pose_world[:2] - placed)))
            spread = position_spread_m(h.covariance_px1)
            rows.append((error, spread, h.n_inliers, h.reprojection_error_px))
    return np.array(rows, dtype=np.float64).reshape(-1, 4)


def summary(rows: np.ndarray) -> dict:
    from scipy.stats import spearmanr

    error, spread, inliers, reprojection = rows.T
    small = spread <= np.median(spread)

    def rho(x):
        return float(spearmanr(error, x)[0])

    return {
        "hypotheses": len(rows),
        "spearman_error_vs_spread": rho(spread),
        "spearman_error_vs_inv_sqrt_inliers": rho(1.0 / np.sqrt(inliers)),
        "spearman_error_vs_reprojection": rho(reprojection),
        "error_quartiles_m": np.quantile(error, [0.25, 0.5, 0.75]).tolist(),
        "spread_quartiles_m": np.quantile(spread, [0.25, 0.5, 0.75]).tolist(),
        "off_share_small_spread": float(np.mean(error[small] > OFF_M)),
        "off_share_large_spread": float(np.mean(error[~small] > OFF_M)),
        "pixel_noise_px": float(np.median(error / spread)),
    }


VARIANTS = {False: "every inlier at 1 px", True: "inliers at their pyramid scale"}


def print_summary(name: str, s: dict) -> None:
    q_e, q_s = s["error_quartiles_m"], s["spread_quartiles_m"]
    print(
        f"{name}: {s['hypotheses']} hypotheses; Spearman of the position error with the "
        f"spread {s['spearman_error_vs_spread']:.2f}, with 1/sqrt(inliers) "
        f"{s['spearman_error_vs_inv_sqrt_inliers']:.2f}, with the reprojection error "
        f"{s['spearman_error_vs_reprojection']:.2f}; error quartiles "
        + " / ".join(f"{v:.3f}" for v in q_e)
        + " m, spread "
        + " / ".join(f"{v:.3f}" for v in q_s)
        + f" m; > {OFF_M} m: {100 * s['off_share_small_spread']:.1f} % of the smaller-spread"
        f" half, {100 * s['off_share_large_spread']:.1f} % of the larger; error / spread "
        f"median {s['pixel_noise_px']:.2f} px",
        flush=True,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_city_arguments(parser)
    args = parser.parse_args()
    limit_threads()
    from bench.lab.evaluation import MemoryMap
    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.server.vision.vocabulary import load_default_vocabulary

    root = city_root(args)
    runs = ("map", "query", "train", "night", "nightmap", "trainnight")
    meta = ensure_dataset(root, args.size, args.frames, args.seed, runs)
    truth = true_poses(meta, args)
    memory = MemoryMap.empty(load_default_vocabulary())
    map_id = sequence_of(meta, "map")
    memory.add_run(read_kitti_sequence(root, map_id))
    map_written = written_poses(root, map_id)
    report = {"dataset": root.name, "off_m": OFF_M}
    t0 = time.time()
    rows_by = {}
    for run in ("query", "night"):
        query = read_kitti_sequence(root, sequence_of(meta, run))
        map_true, written = truth["map"], map_written
        if run == "night":
            nightmap_id = sequence_of(meta, "nightmap")
            memory.add_run(read_kitti_sequence(root, nightmap_id), tags=("night",))
            map_true = np.concatenate([map_true, truth["nightmap"]])
            written = np.concatenate([written, written_poses(root, nightmap_id)])
        for scales in (False, True):
            rows = measure(
                memory, query, query.intrinsics, truth[run], written, map_true, 0, scales
            )
            rows_by[run, scales] = rows
            s = summary(rows)
            name = f"{run}, {VARIANTS[scales]}"
            report[name] = s
            print_summary(name, s)
    for scales in (False, True):
        both = np.concatenate([rows_by["query", scales], rows_by["night", scales]])
        s = summary(both)
        ratio = (
            report[f"night, {VARIANTS[scales]}"]["pixel_noise_px"]
            / (report[f"query, {VARIANTS[scales]}"]["pixel_noise_px"])
        )
        s["night_over_day_pixel_noise"] = ratio
        name = f"query + night, {VARIANTS[scales]}"
        report[name] = s
        print_summary(name, s)
        print(f"  night / day error-to-spread ratio: {ratio:.2f}", flush=True)
    print(f"done in {time.time() - t0:.0f} s")
    out = Path(__file__).parent / "results" / "pose_covariance.json"
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

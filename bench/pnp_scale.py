"""Per-entry PnP accuracy: the keypoints' pyramid scales as LM weights, and the refit on
matches by projection, each beside the plain pose.

A keypoint ORB finds on pyramid level L is located to about scale_factor ** L pixels,
and night frames hold more coarse-level keypoints than day frames.
``PnpConfig.scale_weighting`` (off by default; see its docstring for why) weighs each
reprojection error by 1 / scale^2 when the caller gives the scales (the server's
localizer does). This bench measures what that buys on an urban sim city (the held-out
one by default, generated if missing): for every ``--step``-th frame of the day query
(against the map's entries) and of the night query (against the night entries), the k
retrieved entries are matched and each entry's relative pose T_ref_from_query is
estimated twice from the same matches and the same RANSAC samples, with and without the
scales. Each is judged against the sim's true relative pose (its written poses carry
recording errors; the true ones are re-planned from the seed,
``monoloc.sim.urban.truth``). Entries whose pose either run rejects, or puts more than 2
m off, are left out of both. The plain pose is then refit on the entry's points matched
by projection from it (``LocalizeConfig.refine_by_projection``, the localizer's default:
``server.localize``), and judged the same way ("refined").

Prints the median, mean and 75th percentile of the translation error of each, day and
night, and the median inliers of the plain and the refined poses. Also what the matches
are, per ORB pyramid level of the query keypoint: the share of the right matches (within
``RIGHT_MATCH_PX`` of the true projection of their 3D point) on that level and their
median residual under the true pose, plus the share of all matches that are right; and
what the refined poses kept as inliers: the share of them beyond ``RIGHT_MATCH_PX`` of
their true projection (wrong matches, or map points whose depth is off, that fall within
PnP's threshold around the found pose) and their median residual under the true pose.
Writes bench/results/pnp_scale.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from bench.accuracy import add_city_arguments, city_root, ensure_dataset, limit_threads

RIGHT_POSE_M = 2.0
RIGHT_MATCH_PX = 3.0


def true_camera_poses_by_run(meta: dict, size: str, seed: int, frames: int):
    """The sim's true camera poses (N, 4, 4) per run kind, in the dataset's z-up world."""
    from monoloc.core.geometry import invert_rigid
    from monoloc.sim.generate import GenerateConfig
    from monoloc.sim.urban.city import build_city
    from monoloc.sim.urban.runs import plan_runs, true_camera_poses

    runs = tuple(seq["run"] for seq in meta["sequences"])
    config = GenerateConfig(scenario="urban", size=size, seed=seed, runs=runs, max_frames=frames)
    city = build_city(config.city_config(), seed)
    T_zup_from_sim = invert_rigid(np.asarray(meta["T_simworld_from_zupworld"], dtype=np.float64))
    return {
        p.kind: T_zup_from_sim @ true_camera_poses(p, config.rig) for p in plan_runs(city, config)
    }


def entry_truth(memory, written_positions: np.ndarray, true_poses: np.ndarray) -> dict:
    """Entry id -> the true pose of the frame it was built from (the frame whose written
    position is the entry's)."""
    out = {}
    for entry_id, ref in memory.refs.items():
        frame = int(
            np.argmin(np.linalg.norm(written_positions - ref.T_world_from_cam[:3, 3], axis=1))
        )
        out[entry_id] = true_poses[frame]
    return out


def measure(root: Path, ids: dict, truth: dict, query_run: str, map_run: str, step: int) -> dict:
    """Translation errors (m) of the per-entry poses with and without the scales, and
    every match's residual (px) under the true pose with its query keypoint's scale."""
    from bench.lab.evaluation import EvalConfig, MemoryMap
    from monoloc.core.geometry import invert_rigid
    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.server.vision.binary_code import vlad_binary_code
    from monoloc.server.vision.features import extract_features
    from monoloc.server.vision.pnp import estimate_relative_pose
    from monoloc.server.vision.projection import KeypointGrid, refine_by_projection
    from monoloc.server.vision.vlad import compute_vlad
    from monoloc.server.vision.vocabulary import load_default_vocabulary

    vocabulary = load_default_vocabulary()
    memory = MemoryMap.empty(vocabulary)
    map_seq = read_kitti_sequence(root, ids[map_run])
    memory.add_run(map_seq)
    written = np.array([f.T_world_from_cam[:3, 3] for f in map_seq.frames])
    ref_truth = entry_truth(memory, written, truth[map_run])
    query = read_kitti_sequence(root, ids[query_run])
    config = EvalConfig().localize
    weighted_pnp = dataclasses.replace(config.pnp, scale_weighting=True)
    window = config.refine_by_projection
    errors = {"weighted": [], "unweighted": [], "refined": []}
    inliers = {"unweighted": [], "refined": []}
    residuals_px, scales_of_matches, inlier_residuals_px = [], [], []
    for i in range(0, len(query.frames), step):
        image = query.load(query.frames[i]).image_gray
        features = extract_features(image, config.orb, scales=True)
        vlad = compute_vlad(features.descriptors, vocabulary)
        found = config.preset.retrieve(memory.index, vlad, vlad_binary_code(vlad), config.k, None)
        refs = memory.lookup(found.entry_ids.tolist())
        matches = config.preset.match(
            features.descriptors, [r.descriptors for r in refs], config.match
        )
        grid = KeypointGrid(
            features.keypoints_px, features.descriptors, query.intrinsics, window.radius_px
        )
        for ref, pairs in zip(refs, matches, strict=True):
            pixels = features.keypoints_px[pairs[:, 0]]
            points = ref.points_cam[pairs[:, 1]]
            T_ref_from_query_true = invert_rigid(ref_truth[ref.entry_id]) @ truth[query_run][i]
            residuals_px.append(true_residuals_px(points, pixels, T_ref_from_query_true, query))
            scales_of_matches.append(features.scales[pairs[:, 0]])
            got, plain = {}, None
            for name, scales in (("weighted", features.scales[pairs[:, 0]]), ("unweighted", None)):
                rng = np.random.default_rng((i, ref.entry_id))  # same RANSAC samples for both
                rel = estimate_relative_pose(
                    pixels, points, query.intrinsics, weighted_pnp, rng, scales
                )
                if rel.accepted:
                    got[name] = float(
                        np.linalg.norm(rel.T_ref_from_query[:3, 3] - T_ref_from_query_true[:3, 3])
                    )
                    plain = rel if scales is None else plain
            if len(got) == 2 and max(got.values()) <= RIGHT_POSE_M:
                found = refine_by_projection(
                    grid, ref.descriptors, ref.points_cam, plain, config.pnp, window
                )
                kept_pairs, refined = (pairs, plain) if found is None else found
                kept = kept_pairs[refined.inlier_mask]
                inlier_residuals_px.append(
                    true_residuals_px(
                        ref.points_cam[kept[:, 1]],
                        features.keypoints_px[kept[:, 0]],
                        T_ref_from_query_true,
                        query,
                    )
                )
                got["refined"] = float(
                    np.linalg.norm(refined.T_ref_from_query[:3, 3] - T_ref_from_query_true[:3, 3])
                )
                for name, error in got.items():
                    errors[name].append(error)
                inliers["unweighted"].append(plain.n_inliers)
                inliers["refined"].append(refined.n_inliers)
    out = {name: np.array(values) for name, values in errors.items()}
    out["inliers"] = {name: float(np.median(values)) for name, values in inliers.items()}
    out["residuals_px"] = np.concatenate(residuals_px)
    out["scales"] = np.concatenate(scales_of_matches)
    out["inlier_residuals_px"] = np.concatenate(inlier_residuals_px)
    return out


def true_residuals_px(points_ref, pixels, T_ref_from_query, query) -> np.ndarray:
    """Reprojection residual (M,) px of each match under the true relative pose (inf for
    a point behind the query camera)."""
    from monoloc.core.geometry import invert_rigid
    from monoloc.server.vision.depth import project_points

    T = invert_rigid(T_ref_from_query)
    points_query = np.asarray(points_ref, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
    in_front = points_query[:, 2] > 0.1
    residuals = np.full(len(points_query), np.inf)
    projected = project_points(points_query[in_front], query.intrinsics)
    residuals[in_front] = np.linalg.norm(projected - np.asarray(pixels)[in_front], axis=1)
    return residuals


def by_level(residuals_px: np.ndarray, scales: np.ndarray, scale_factor: float) -> dict:
    """Share of all matches that are right, and per pyramid level the right matches'
    share and median residual."""
    right = residuals_px <= RIGHT_MATCH_PX
    levels = np.rint(np.log(scales) / np.log(scale_factor)).astype(int)
    rows = {}
    for level in range(int(levels.max()) + 1):
        on = right & (levels == level)
        if on.any():
            rows[str(level)] = {
                "share_of_right": float(on.sum() / right.sum()),
                "median_residual_px": float(np.median(residuals_px[on])),
            }
    return {"matches": int(len(right)), "right_share": float(right.mean()), "levels": rows}


def summary(errors: np.ndarray) -> dict:
    return {
        "n": int(len(errors)),
        "median_m": float(np.median(errors)),
        "mean_m": float(np.mean(errors)),
        "p75_m": float(np.percentile(errors, 75)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_city_arguments(parser)
    parser.add_argument("--step", type=int, default=5, help="every step-th query frame")
    args = parser.parse_args()
    limit_threads()
    root = city_root(args)
    runs = ("map", "query", "train", "night", "offcenter", "nightmap")
    meta = ensure_dataset(root, args.size, args.frames, args.seed, runs)
    ids = {seq["run"]: seq["id"] for seq in meta["sequences"]}
    truth = true_camera_poses_by_run(meta, args.size, args.seed, args.frames)
    report = {"dataset": root.name, "step": args.step}
    t0 = time.time()
    for label, query_run, map_run in (("day", "query", "map"), ("night", "night", "nightmap")):
        if map_run not in ids:
            print(f"{label}: the dataset has no {map_run} run; skipped")
            continue
        errors = measure(root, ids, truth, query_run, map_run, args.step)
        rows = {name: summary(errors[name]) for name in ("weighted", "unweighted", "refined")}
        from monoloc.server.vision.features import OrbConfig

        matches = by_level(errors["residuals_px"], errors["scales"], OrbConfig().scale_factor)
        kept = errors["inlier_residuals_px"]
        inliers_true = {
            "n": int(len(kept)),
            "wrong_share": float(np.mean(kept > RIGHT_MATCH_PX)),
            "median_residual_px": float(np.median(kept)),
        }
        report[label] = {
            **rows,
            "inliers_median": errors["inliers"],
            "matches": matches,
            "refined_inliers": inliers_true,
        }
        w, u = rows["weighted"], rows["unweighted"]
        print(
            f"{label}: {w['n']} entry poses; translation error median {w['median_m']:.4f} m "
            f"(without scales {u['median_m']:.4f}), mean {w['mean_m']:.4f} "
            f"({u['mean_m']:.4f}), p75 {w['p75_m']:.4f} ({u['p75_m']:.4f})",
            flush=True,
        )
        r = rows["refined"]
        print(
            f"  refined by projection: median {r['median_m']:.4f} m (plain {u['median_m']:.4f}), "
            f"mean {r['mean_m']:.4f} ({u['mean_m']:.4f}), p75 {r['p75_m']:.4f} "
            f"({u['p75_m']:.4f}); inliers median {errors['inliers']['refined']:.0f} "
            f"({errors['inliers']['unweighted']:.0f})",
            flush=True,
        )
        levels = matches["levels"]
        coarse = sum(levels.get(str(k), {}).get("share_of_right", 0.0) for k in (5, 6, 7))
        print(
            f"  {matches['matches']} matches, {matches['right_share']:.0%} within "
            f"{RIGHT_MATCH_PX:g} px of the true projection; of those, {coarse:.0%} from levels "
            "5-7; median residual per level: "
            + ", ".join(f"{k}: {v['median_residual_px']:.2f}" for k, v in levels.items())
            + " px",
            flush=True,
        )
        print(
            f"  the refined poses' {inliers_true['n']} inliers: "
            f"{inliers_true['wrong_share']:.1%} beyond {RIGHT_MATCH_PX:g} px of their true "
            f"projection, median true residual {inliers_true['median_residual_px']:.2f} px",
            flush=True,
        )
    print(f"done in {time.time() - t0:.0f} s")
    out = Path(__file__).parent / "results" / "pnp_scale.json"
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

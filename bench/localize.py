"""Per-query localization time at KITTI resolution, k = 10, on one core, beside the
paper-faithful pipeline.

Data: a sim city's map pass (100 frames, 1241 x 376, ingested into a fresh SQLite map)
and its query pass (100 frames driven later with lateral offsets, other parked cars and
light), generated once into ``out/bench_sim`` (shared with bench/ingest.py).

Pipelines, same features, VLAD and entry cache:
- monoloc (``server.localize.localize_frame`` through ``MapRegistry``): binary index
  (Hamming shortlist, exact float re-rank), compiled Hamming matching, guided PnP and the
  joint pose (no prior given here, so the entry with the most matches gets a full RANSAC);
- monoloc with independent PnP (every entry its own RANSAC, no joint pose): the PnP
  baseline of guided PnP, same run;
- paper-faithful: exact float k-NN over all VLADs (numpy) and OpenCV brute-force
  matching (``cv2.BFMatcher(NORM_HAMMING).knnMatch``, ``match_descriptors_bruteforce``).

One core: cv2.setNumThreads(1), faiss.omp_set_num_threads(1), threadpool_limits(1).
Each query is localized ``PASSES`` times after one warm-up pass (entries cached, as in a
running server); the table gives p50 and p99 per stage and in total, plus accuracy
(share of queries whose best hypothesis is within 0.3 m of ground truth; recall@10:
a retrieved entry within 2 m). Goals (issue 17): p50 total <= 20 ms, <= 2.0x the
blur+ORB stage ("features") alone, >= 5x faster than the paper-faithful pipeline, p99 <=
2x p50. Writes bench/results/localize.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

if sys.path and Path(sys.path[0]).resolve() == Path(__file__).parent.resolve():
    sys.path.pop(0)  # bench/sim.py would shadow the sim package

import numpy as np  # noqa: E402

RESULTS = Path(__file__).parent / "results"
DEFAULT_DATA = Path(__file__).parent.parent / "out" / "bench_sim"
PASSES = 3
K = 10
TARGET_P50_MS = 20.0
GOAL_X_FEATURES = 2.0
GOAL_X_PAPER = 5.0
GOAL_P99_OVER_P50 = 2.0
STAGES = ("features", "vlad", "retrieval", "lookup", "matching", "pnp", "total")


def paper_localize(image, intrinsics, vocabulary, ids, vlads, lookup, config, rng, k):
    """Same steps as localize_frame, with exact float k-NN and OpenCV brute-force matching.
    Returns (best position (2,) or None, retrieved ids, timings_ms)."""
    from monoloc.server.vision.features import extract_features
    from monoloc.server.vision.hypothesis import compose_hypothesis
    from monoloc.server.vision.matching import match_descriptors_bruteforce
    from monoloc.server.vision.pnp import estimate_relative_pose
    from monoloc.server.vision.vlad import compute_vlad

    timings, clock = {}, [time.perf_counter()]
    start = clock[0]

    def lap(name):
        now = time.perf_counter()
        timings[name] = (now - clock[0]) * 1e3
        clock[0] = now

    features = extract_features(image, config.orb)
    lap("features")
    vlad = compute_vlad(features.descriptors, vocabulary)
    lap("vlad")
    d2 = np.einsum("ij,ij->i", vlads - vlad, vlads - vlad)
    top = np.argpartition(d2, min(k, len(d2) - 1))[:k]
    found = ids[top[np.argsort(d2[top])]]
    lap("retrieval")
    refs = lookup(found.tolist())
    lap("lookup")
    pairs = [
        match_descriptors_bruteforce(features.descriptors, r.descriptors, config.match)
        for r in refs
    ]
    lap("matching")
    best, best_inliers = None, -1
    for ref, match in zip(refs, pairs, strict=True):
        rel = estimate_relative_pose(
            features.keypoints_px[match[:, 0]],
            ref.points_cam[match[:, 1]],
            intrinsics,
            config.pnp,
            rng,
        )
        if rel.accepted and rel.n_inliers > best_inliers:
            best_inliers = rel.n_inliers
            best = compose_hypothesis(ref.T_world_from_cam, rel.T_ref_from_query)[:2, 3]
    lap("pnp")
    timings["total"] = (time.perf_counter() - start) * 1e3
    return best, found, timings


def summarise(samples: list[dict]) -> dict:
    return {
        s: {
            "p50_ms": float(np.percentile([t[s] for t in samples], 50)),
            "p99_ms": float(np.percentile([t[s] for t in samples], 99)),
        }
        for s in STAGES
    }


def check_goals(table: dict) -> dict:
    """The goals of issue 17 on this run's p50 / p99 (ms), each with its figure."""
    m = table["monoloc"]
    total, p99 = m["total"]["p50_ms"], m["total"]["p99_ms"]
    x_features = total / m["features"]["p50_ms"]
    x_paper = table["paper"]["total"]["p50_ms"] / total
    x_p99 = p99 / total
    pnp_gain = table["independent"]["pnp"]["p50_ms"] / m["pnp"]["p50_ms"]
    met = {
        "p50_target": total <= TARGET_P50_MS,
        "x_features": x_features <= GOAL_X_FEATURES,
        "x_paper": x_paper >= GOAL_X_PAPER,
        "p99_over_p50": x_p99 <= GOAL_P99_OVER_P50,
    }

    def verdict(key):
        return "met" if met[key] else "NOT met"

    return {
        "total_p50_ms": total,
        "total_over_features": x_features,
        "paper_over_total": x_paper,
        "p99_over_p50": x_p99,
        "pnp_independent_over_guided": pnp_gain,
        "met": met,
        "lines": [
            f"goal p50 <= {TARGET_P50_MS:.0f} ms: {verdict('p50_target')} ({total:.1f} ms)",
            f"goal p50 <= {GOAL_X_FEATURES:.1f}x blur+ORB: {verdict('x_features')} "
            f"({x_features:.2f}x of {m['features']['p50_ms']:.2f} ms)",
            f"goal >= {GOAL_X_PAPER:.0f}x faster than paper-faithful: {verdict('x_paper')} "
            f"({x_paper:.2f}x; paper-faithful {table['paper']['total']['p50_ms']:.1f} ms)",
            f"goal p99 <= {GOAL_P99_OVER_P50:.0f}x p50: {verdict('p99_over_p50')} ({x_p99:.2f}x)",
            f"guided PnP vs independent PnP (same run): {pnp_gain:.2f}x faster at p50",
        ],
    }


def ensure_dataset(root: Path, frames: int = 100) -> Path:
    """The sim city of bench/ingest.py (map 00 and query 01 at KITTI resolution)."""
    if not (root / "dataset.json").exists():
        from monoloc.sim.generate import GenerateConfig, generate_dataset

        print(f"generating {frames} + {frames} frames into {root} (once) ...", flush=True)
        generate_dataset(GenerateConfig(seed=0, runs=("map", "query"), max_frames=frames), root)
    return root


def build_registry(workdir: Path, map_run):
    from monoloc.server.ingest.manage import create_map, ingest_source
    from monoloc.server.runtime import MapRegistry
    from monoloc.server.settings import Settings
    from monoloc.server.storage.db import create_engine_for, make_session_factory
    from monoloc.server.storage.migrate import upgrade_database

    settings = Settings(data_dir=workdir)
    upgrade_database(settings.database_url)
    factory = make_session_factory(create_engine_for(settings))
    map_id = create_map(factory, "bench", map_run.intrinsics).id
    ingest_source(factory, map_id, map_run)
    return MapRegistry(factory, settings.index_dir, version_check_s=1e9), map_id


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--passes", type=int, default=PASSES)
    args = parser.parse_args()

    import cv2
    import faiss
    from threadpoolctl import threadpool_limits

    from monoloc.core.geometry import planar_from_T_world_from_cam
    from monoloc.server.ingest.kitti import read_kitti_sequence
    from monoloc.server.localize import LocalizeConfig

    root = ensure_dataset(args.data)
    map_run, query_run = read_kitti_sequence(root, "00"), read_kitti_sequence(root, "01")
    with tempfile.TemporaryDirectory() as tmp:
        registry, map_id = build_registry(Path(tmp), map_run)
        runtime = registry.get(map_id)
        snapshot = runtime.index.snapshot()
        ids, vlads, poses = snapshot["ids"], snapshot["vlads"], snapshot["poses"]
        queries = []
        for frame in query_run.frames:
            truth = planar_from_T_world_from_cam(frame.T_world_from_cam)[:2]
            if np.min(np.linalg.norm(poses[:, :2] - truth, axis=1)) <= 2.0:
                queries.append((query_run.load(frame).image_gray, truth))
        config = LocalizeConfig(k=K)
        independent = LocalizeConfig(k=K, guided_pnp=False, joint=None)
        cv2.setNumThreads(1)
        faiss.omp_set_num_threads(1)
        names = ("monoloc", "independent", "paper")
        results = {n: [] for n in names}
        accuracy = {n: [] for n in names}
        recall = {n: [] for n in names}
        xy_of = dict(zip(ids.tolist(), poses[:, :2], strict=True))
        load_before = os.getloadavg()
        with threadpool_limits(1):
            for p in range(args.passes + 1):  # pass 0 warms the entry cache up
                rng = np.random.default_rng(p)
                for image, truth in queries:
                    result, _ = registry.localize(map_id, image, config, rng, k=K)
                    best = result.best
                    xy, found = (
                        (None if best is None else best.pose_world[:2]),
                        result.retrieved_ids,
                    )
                    runs = [("monoloc", xy, found, result.timings_ms)]
                    plain, _ = registry.localize(map_id, image, independent, rng, k=K)
                    runs.append(
                        (
                            "independent",
                            None if plain.best is None else plain.best.pose_world[:2],
                            plain.retrieved_ids,
                            plain.timings_ms,
                        )
                    )
                    runs.append(
                        (
                            "paper",
                            *paper_localize(
                                image,
                                runtime.record.camera,
                                runtime.vocabulary,
                                ids,
                                vlads,
                                runtime.cache.get,
                                config,
                                rng,
                                K,
                            ),
                        )
                    )
                    if p == 0:
                        continue
                    for name, xy, found, timings in runs:
                        results[name].append(timings)
                        ok = xy is not None and np.linalg.norm(np.asarray(xy) - truth) <= 0.3
                        accuracy[name].append(ok)
                        recall[name].append(
                            any(np.linalg.norm(xy_of[i] - truth) <= 2.0 for i in found.tolist())
                        )
    table = {name: summarise(samples) for name, samples in results.items()}
    print(
        f"\nlocalization of {len(queries)} query frames x {args.passes} passes, "
        f"{map_run.intrinsics.width_px}x{map_run.intrinsics.height_px}, k={K}, "
        f"{len(ids)} map entries, one thread; load average before {load_before[0]:.2f}"
    )
    print(
        f"{'stage':<10} {'monoloc p50':>12} {'p99':>8}   {'indep. PnP p50':>14} {'p99':>8}   "
        f"{'paper p50':>10} {'p99':>8}"
    )
    for stage in STAGES:
        m, i, b = (table[n][stage] for n in names)
        print(
            f"{stage:<10} {m['p50_ms']:10.2f}ms {m['p99_ms']:6.1f}ms   "
            f"{i['p50_ms']:12.2f}ms {i['p99_ms']:6.1f}ms   "
            f"{b['p50_ms']:8.2f}ms {b['p99_ms']:6.1f}ms"
        )
    share = {k: float(np.mean(v)) for k, v in accuracy.items()}
    rec = {k: float(np.mean(v)) for k, v in recall.items()}
    print(
        "best hypothesis within 0.3 m: "
        + ", ".join(f"{n} {share[n]:.2f}" for n in names)
        + "; recall@10 (2 m): "
        + ", ".join(f"{n} {rec[n]:.2f}" for n in names)
    )
    goals = check_goals(table)
    for line in goals["lines"]:
        print(line)
    RESULTS.mkdir(exist_ok=True)
    out = {
        "queries": len(queries),
        "passes": args.passes,
        "k": K,
        "map_entries": len(ids),
        "image": [map_run.intrinsics.width_px, map_run.intrinsics.height_px],
        "load_average_before": load_before,
        "machine": platform.platform(),
        "target_p50_ms": TARGET_P50_MS,
        "goals": {k: v for k, v in goals.items() if k != "lines"},
        "stages": table,
        "share_within_0_3m": share,
        "recall_at_10": rec,
    }
    (RESULTS / "localize.json").write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {RESULTS / 'localize.json'}")


if __name__ == "__main__":
    main()

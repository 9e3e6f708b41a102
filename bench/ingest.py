"""Ingestion throughput at KITTI resolution, beside a single-threaded baseline.

Data: the ``map`` pass of a sim city, 100 frames of 1241 x 376 with 64-beam LiDAR scans
(generated once into ``out/bench_sim``; ``--data`` to use another KITTI-layout root).
Each variant ingests the whole sequence into a fresh SQLite map (same vocabulary, same
entries) and is timed end to end (hashing, decoding, ORB, LiDAR association, VLAD,
database writes):

- baseline: the same steps, one frame after another on one thread (read, build the
  entry, add it; commit every 24 frames);
- pipeline, 1 worker: ``monoloc.server.ingest.pipeline.ingest_run`` with one build thread (DB
  writes overlap on the calling thread);
- pipeline, 2 workers: the product setting on a 2-core machine.

Target: >= 20 frames/s with 2 workers on 2 cores. OpenCV and BLAS run one thread per
worker (threadpoolctl) so the cores are not oversubscribed. ``REPEATS`` runs per
variant; the table gives the median and the best (other processes on a shared machine
only ever slow a run down). Writes bench/results/ingest.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import tempfile
import time
from pathlib import Path

RESULTS = Path(__file__).parent / "results"
DEFAULT_DATA = Path(__file__).parent.parent / "out" / "bench_sim"
FRAMES = 100
REPEATS = 3
TARGET_FPS = 20.0


def ensure_dataset(root: Path, frames: int = FRAMES) -> Path:
    """A sim city with map (00) and query (01) passes at KITTI resolution (cached)."""
    if (root / "dataset.json").exists():
        return root
    from monoloc.sim.generate import GenerateConfig, generate_dataset

    print(f"generating {frames} + {frames} frames into {root} (once) ...", flush=True)
    generate_dataset(GenerateConfig(seed=0, runs=("map", "query"), max_frames=frames), root)
    return root


def _fresh_map(workdir: Path, source):
    from monoloc.server.ingest.manage import create_map
    from monoloc.server.settings import Settings
    from monoloc.server.storage.db import create_engine_for, make_session_factory
    from monoloc.server.storage.migrate import upgrade_database

    shutil.rmtree(workdir, ignore_errors=True)
    settings = Settings(data_dir=workdir)
    upgrade_database(settings.database_url)
    factory = make_session_factory(create_engine_for(settings))
    return factory, create_map(factory, "bench", source.intrinsics).id


def run_baseline(workdir: Path, source) -> tuple[float, int]:
    """Everything on the calling thread, frame by frame."""
    import hashlib

    import cv2
    import numpy as np
    from threadpoolctl import threadpool_limits

    from monoloc.server.entry_builder import BuildConfig, TooFewPointsError, build_entry
    from monoloc.server.storage import entries as entries_repo
    from monoloc.server.storage import maps as maps_repo
    from monoloc.server.storage.db import session_scope
    from monoloc.server.vision.vocabulary import Vocabulary

    factory, map_id = _fresh_map(workdir, source)
    start = time.perf_counter()
    with session_scope(factory) as session:
        vocab = maps_repo.get_vocabulary(session, maps_repo.get_map(session, map_id).vocabulary_id)
    vocabulary = Vocabulary.from_centres(np.asarray(vocab.centres))
    cv2.setNumThreads(1)
    added, pending = 0, []
    with threadpool_limits(1):
        for i, frame in enumerate(source.frames):
            loaded = source.load(frame)
            digest = hashlib.sha256(loaded.image_bytes).hexdigest()
            try:
                pending.append(
                    build_entry(
                        loaded.image_gray,
                        digest,
                        frame.T_world_from_cam,
                        loaded.source,
                        source.intrinsics,
                        vocabulary,
                        vocab.id,
                        BuildConfig(),
                        timestamp_s=frame.timestamp_s,
                    )
                )
            except TooFewPointsError:
                pass
            if len(pending) == 24 or i == len(source.frames) - 1:
                with session_scope(factory) as session:
                    for entry in pending:
                        added += entries_repo.add_entry(session, map_id, entry)[1]
                pending = []
    return time.perf_counter() - start, added


def run_pipeline(workdir: Path, source, workers: int) -> tuple[float, int]:
    from monoloc.server.ingest.manage import ingest_source
    from monoloc.server.ingest.pipeline import IngestConfig

    factory, map_id = _fresh_map(workdir, source)
    start = time.perf_counter()
    summary = ingest_source(factory, map_id, source, config=IngestConfig(workers=workers))
    return time.perf_counter() - start, summary.entries_added


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--repeats", type=int, default=REPEATS)
    args = parser.parse_args()
    from monoloc.server.ingest.sources import read_kitti_sequence

    source = read_kitti_sequence(ensure_dataset(args.data), "00")
    n = source.n_frames
    variants = {
        "baseline (1 thread, sequential)": lambda d: run_baseline(d, source),
        "pipeline, 1 worker": lambda d: run_pipeline(d, source, 1),
        "pipeline, 2 workers": lambda d: run_pipeline(d, source, 2),
    }
    load_before = os.getloadavg()
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, run in variants.items():
            times, entries = [], 0
            for r in range(args.repeats):
                elapsed, entries = run(Path(tmp) / f"run{r}")
                times.append(elapsed)
            rows[name] = {
                "median_fps": n / statistics.median(times),
                "best_fps": n / min(times),
                "times_s": times,
                "entries": entries,
            }
    base = rows["baseline (1 thread, sequential)"]["median_fps"]
    width = max(len(k) for k in rows)
    print(
        f"\ningestion of {n} frames at {source.intrinsics.width_px}x"
        f"{source.intrinsics.height_px} (+ LiDAR), {os.cpu_count()} cores, "
        f"load average before {load_before[0]:.2f}"
    )
    print(f"{'variant':<{width}}  median fps  best fps  speed-up  entries")
    for name, row in rows.items():
        print(
            f"{name:<{width}}  {row['median_fps']:10.1f}  {row['best_fps']:8.1f}  "
            f"{row['median_fps'] / base:7.2f}x  {row['entries']:7d}"
        )
    product = rows["pipeline, 2 workers"]["median_fps"]
    print(
        f"target >= {TARGET_FPS:.0f} frames/s with 2 workers: "
        f"{'met' if product >= TARGET_FPS else 'NOT met'} ({product:.1f})"
    )
    RESULTS.mkdir(exist_ok=True)
    out = {
        "frames": n,
        "image": [source.intrinsics.width_px, source.intrinsics.height_px],
        "cpu_count": os.cpu_count(),
        "load_average_before": load_before,
        "machine": platform.platform(),
        "target_fps": TARGET_FPS,
        "variants": rows,
    }
    (RESULTS / "ingest.json").write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {RESULTS / 'ingest.json'}")


if __name__ == "__main__":
    main()

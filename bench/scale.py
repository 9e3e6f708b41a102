"""A city on one replica (issue 52, 1): a map of ``--entries`` entries built end to end,
measured beside the same figures at the smaller ``--sizes`` in the same run (the first is
the baseline; the map grows from one size to the next).

1. Base: sim cities of several seeds (map + query runs, KITTI size) are rendered and
   their map runs ingested through the real pipeline (``ingest_source``): one source map
   per city; the pipeline's entries/s is reported.
2. ``monoloc map bulk-tile``'s functions (server/ingest/bulk.py) tile the sources into map
   ``scale``: up to each size in turn, measured at each.
3. At each size: disk (SQLite file, or ``pg_database_size``); index rebuild from the
   database (``persist.rebuild_index``, in this process); recall@10 of the index against
   exact float search (numpy over the database's VLADs, chunked) for the query frames'
   VLADs, with and without a prior; then a real ``monoloc serve`` process: cold start
   (process start -> first localize answer, no index file), its RssAnon / RssFile, query
   p50/p99 over HTTP with a prior (on the source's tile, and on a turned, perturbed copy)
   and without one, and a warm restart (the index files kept).

``--database postgresql`` runs a throwaway PostgreSQL server (tests/pg_cluster.py) with its
data under ``--work-dir``. Data lives in ``--work-dir`` (deleted at the end unless ``--keep``;
the rendered base is kept for the next run). Writes bench/results/scale_<database>_<entries>.json
after each size (a run stopped early keeps the sizes done).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
ADMIN_KEY = "mlk_" + "S" * 43
PRIOR_RADIUS_M = 20.0
K = 10


@dataclass(frozen=True)
class QueryFrame:
    """One query frame of a base city: its PNG, its VLAD and code (as the server computes
    them), its true pose (4, 4) in its city's frame and the source it belongs to."""

    png: bytes
    vlad: np.ndarray
    code: np.ndarray
    T_world_from_cam: np.ndarray
    source: int


def load() -> str:
    return Path("/proc/loadavg").read_text().split(" ")[0]


def free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def git(*args: str) -> str:
    done = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, timeout=30)
    return done.stdout.strip()


# ---- base -------------------------------------------------------------------------------
def render_base(work: Path, seeds: list[int], frames: int) -> list[Path]:
    """One dataset per seed (kept between runs: a marker names its settings)."""
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.lidar import LidarConfig

    roots = []
    for seed in seeds:
        root = work / "base" / f"city_{seed}"
        marker = root / "scale-base.json"
        wanted = {"seed": seed, "frames": frames, "runs": ["map", "query"], "azimuth": 1500}
        if not (marker.exists() and json.loads(marker.read_text()) == wanted):
            shutil.rmtree(root, ignore_errors=True)
            t0 = time.perf_counter()
            config = GenerateConfig(
                seed=seed,
                runs=("map", "query"),
                max_frames=frames,
                lidar=LidarConfig(azimuth_steps=1500),
            )
            generate_dataset(config, root)
            marker.write_text(json.dumps(wanted))
            print(f"rendered city {seed}: {time.perf_counter() - t0:.0f} s", flush=True)
        roots.append(root)
    return roots


def ingest_base(factory, roots: list[Path], seeds: list[int]) -> dict:
    """Source maps ``city-<seed>`` through the real ingestion pipeline; its rate."""
    from monoloc.server.ingest.manage import create_map, ingest_source
    from monoloc.server.ingest.sources import read_kitti_sequence

    frames = entries = 0
    t0 = time.perf_counter()
    for root, seed in zip(roots, seeds, strict=True):
        run = read_kitti_sequence(root, "00")
        create_map(factory, f"city-{seed}", run.intrinsics)
        summary = ingest_source(factory, f"city-{seed}", run)
        frames += len(run.frames)
        entries += summary.entries_added
    seconds = time.perf_counter() - t0
    return dict(frames=frames, entries=entries, seconds=seconds, entries_per_s=entries / seconds)


def query_frames(roots: list[Path], per_city: int, vocabulary) -> list[QueryFrame]:
    """``per_city`` frames of each city's query run, evenly spread."""
    import cv2

    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.server.localize import LocalizeConfig
    from monoloc.server.vision.binary_code import vlad_binary_code
    from monoloc.server.vision.features import extract_features
    from monoloc.server.vision.vlad import compute_vlad

    orb = LocalizeConfig().orb
    out = []
    for source, root in enumerate(roots):
        run = read_kitti_sequence(root, "01")
        picks = np.linspace(0, len(run.frames) - 1, per_city).round().astype(int)
        for i in picks:
            frame = run.frames[int(i)]
            png = frame.image_path.read_bytes()
            gray = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE)
            vlad = compute_vlad(extract_features(gray, orb, scales=True).descriptors, vocabulary)
            out.append(
                QueryFrame(png, vlad, vlad_binary_code(vlad), frame.T_world_from_cam, source)
            )
    return out


# ---- database ----------------------------------------------------------------------------
@contextmanager
def database(kind: str, work: Path, reuse: bool = False):
    """(Settings of a fresh database, a callable giving its size in bytes); ``reuse``
    (SQLite): the database a run left (``--keep``, or a run stopped early)."""
    from monoloc.server.settings import Settings

    data_dir = work / f"data-{kind}"
    if not reuse:
        shutil.rmtree(data_dir, ignore_errors=True)
    if kind == "sqlite":
        settings = Settings(data_dir=data_dir, bootstrap_admin_key=ADMIN_KEY)
        db_file = data_dir / "monoloc.db"

        def size() -> int:
            return sum(p.stat().st_size for p in data_dir.glob(db_file.name + "*"))

        yield settings, size
        return
    from sqlalchemy import create_engine, text

    sys.path.insert(0, str(ROOT / "tests"))
    from pg_cluster import ThrowawayPostgres, find_pg_bin

    bin_dir = find_pg_bin()
    if bin_dir is None:
        raise SystemExit("no PostgreSQL server installed")
    root = work / "pg"
    shutil.rmtree(root, ignore_errors=True)
    root.mkdir(parents=True)
    os.chmod(root, 0o755)
    server = ThrowawayPostgres(bin_dir, root, free_port())
    server.start()
    try:
        admin = create_engine(server.url, isolation_level="AUTOCOMMIT")
        with admin.connect() as c:
            c.execute(text("CREATE DATABASE monoloc_scale"))
        url = server.url.replace("/postgres?", "/monoloc_scale?")
        settings = Settings(data_dir=data_dir, database_url=url, bootstrap_admin_key=ADMIN_KEY)

        def size() -> int:
            with admin.connect() as c:
                return int(c.execute(text("SELECT pg_database_size('monoloc_scale')")).scalar())

        yield settings, size
        admin.dispose()
    finally:
        server.stop()


# ---- measurements --------------------------------------------------------------------------
def exact_top_k(factory, map_id: int, queries: np.ndarray, priors: list) -> tuple:
    """((Q, K) entry ids nearest by float VLAD L2 over the whole map, (Q, K) inside each
    query's prior disc (-1: fewer inside)), and the (Q, K) map-wide distances, in one
    chunked numpy pass."""
    from monoloc.server.storage import entries as entries_repo
    from monoloc.server.storage.db import session_scope

    q = np.asarray(queries, np.float32)
    best = {kind: (np.full((len(q), K), np.inf), np.full((len(q), K), -1)) for kind in "fp"}
    with session_scope(factory) as session:
        for batch in entries_repo.iter_map_vectors(session, map_id, batch_size=8192):
            v = np.asarray(batch.vlads, np.float32)
            d = (q * q).sum(1)[:, None] - 2.0 * q @ v.T + (v * v).sum(1)[None, :]
            inside = np.stack([p.mask(batch.planar) for p in priors])
            for kind, dist in (("f", d), ("p", np.where(inside, d, np.inf))):
                best_d, best_id = best[kind]
                all_d = np.concatenate([best_d, dist], axis=1)
                ids = np.broadcast_to(batch.entry_ids, dist.shape)
                all_id = np.concatenate([best_id, ids], axis=1)
                keep = np.argsort(all_d, axis=1, kind="stable")[:, :K]
                best[kind] = (
                    np.take_along_axis(all_d, keep, 1),
                    np.take_along_axis(all_id, keep, 1),
                )
    ids = tuple(np.where(np.isfinite(best[k][0]), best[k][1], -1) for k in "fp")
    return ids, np.sqrt(np.maximum(best["f"][0], 0.0))


def recall_at_k(found: list[np.ndarray], exact: np.ndarray) -> float:
    """Mean share of each query's exact top-K (ids != -1) the index returned."""
    shares = []
    for ids, truth in zip(found, exact, strict=True):
        truth = truth[truth >= 0]
        if len(truth):
            shares.append(len(set(ids.tolist()) & set(truth.tolist())) / len(truth))
    return float(np.mean(shares))


def index_figures(settings, factory, map_id: int, queries, priors, work: Path, rebuild: bool):
    """Index rebuild from the database (timed; ``rebuild`` False: the index the server
    saved is loaded instead, its rebuild is the cold start) and recall@10 against exact
    search."""
    from monoloc.server.index.persist import delete_index, load_index, rebuild_index
    from monoloc.server.storage import entries as entries_repo
    from monoloc.server.storage import maps as maps_repo
    from monoloc.server.storage.db import session_scope

    path = work / "bench-index" / "scale.index.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    rebuild_s = None
    with session_scope(factory) as session:
        version = maps_repo.get_map(session, map_id).version
        if rebuild:
            t0 = time.perf_counter()
            index = rebuild_index(path, entries_repo.iter_map_vectors(session, map_id), version)
            rebuild_s = time.perf_counter() - t0
        else:
            index = load_index(settings.index_dir / f"map_{map_id}.index.npz", version)
    vlads = np.stack([q.vlad for q in queries])
    t0 = time.perf_counter()
    (exact_free, exact_prior), exact_d = exact_top_k(factory, map_id, vlads, priors)
    exact_s = time.perf_counter() - t0
    found = [index.search(q.vlad, q.code, K) for q in queries]
    free = [r.entry_ids for r in found]
    # tile copies of one place are near-ties: how much farther the index's k-th is
    ratio_10 = [float(r.distances[-1] / d[-1]) for r, d in zip(found, exact_d, strict=True)]
    with_prior = [
        index.search(q.vlad, q.code, K, p).entry_ids for q, p in zip(queries, priors, strict=True)
    ]
    figures = dict(
        rebuild_s=rebuild_s,
        index_kind=index.kind,
        recall_at_10=recall_at_k(free, exact_free),
        recall_at_10_prior=recall_at_k(with_prior, exact_prior),
        distance_ratio_at_10_mean=float(np.mean(ratio_10)),
        distance_ratio_at_10_max=float(np.max(ratio_10)),
        exact_search_s=exact_s,
        queries=len(queries),
    )
    del index
    if rebuild:
        delete_index(path)
    return figures


def status_kb(pid: int) -> dict[str, int]:
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("RssAnon", "RssFile", "VmHWM"):
            out[key] = int(value.split()[0])
    return out


@contextmanager
def served(settings, first_query: QueryFrame, map_id: int, timeout_s: float):
    """A ``monoloc serve`` process on the settings' database; yields (client, pid,
    seconds from process start to the first localize answer)."""
    from monoloc.client.api import MonolocClient

    port = free_port()
    env = dict(
        os.environ,
        MONOLOC_DATA_DIR=str(settings.data_dir),
        MONOLOC_BOOTSTRAP_ADMIN_KEY=ADMIN_KEY,
        MONOLOC_WORKER_THREADS="1",
        MONOLOC_CV_THREADS="1",
        MONOLOC_FAISS_THREADS="1",
    )
    if settings.database_url and not settings.database_url.startswith("sqlite"):
        env["MONOLOC_DATABASE_URL"] = settings.database_url
    cmd = [sys.executable, "-m", "monoloc.cli", "serve", "--port", str(port)]
    cmd += ["--log-level", "warning"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, cwd=ROOT)
    client = MonolocClient(f"http://127.0.0.1:{port}", ADMIN_KEY, timeout_s=120.0, retries=0)
    try:
        while True:
            if proc.poll() is not None:
                raise SystemExit(f"monoloc serve exited with {proc.returncode}")
            if time.perf_counter() - t0 > timeout_s:
                raise SystemExit(f"no localize answer within {timeout_s} s")
            try:
                client.localize(map_id, first_query.png, seed=1, retries=0)
                break
            except Exception:  # noqa: BLE001 - not listening yet
                time.sleep(0.2)
        yield client, proc.pid, time.perf_counter() - t0
    finally:
        client.close()
        proc.terminate()
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def http_queries(client, map_id: int, queries, priors, expected_xy) -> dict:
    """Latency (ms, p50/p99) and position error of the best hypothesis, sequential."""
    laps, errors = [], []
    for q, prior, xy in zip(queries, priors, expected_xy, strict=True):
        t0 = time.perf_counter()
        answer = client.localize(map_id, q.png, prior=prior, seed=1, retries=0)
        laps.append(1000.0 * (time.perf_counter() - t0))
        best = answer.best_pose_world
        errors.append(
            np.inf if not np.all(np.isfinite(best)) else float(np.hypot(*(best[:2] - xy)))
        )
    errors = np.asarray(errors)
    return dict(
        p50_ms=float(np.percentile(laps, 50)),
        p99_ms=float(np.percentile(laps, 99)),
        within_1m=float(np.mean(errors < 1.0)),
        n=len(laps),
    )


def server_figures(settings, map_id: int, queries, tiles, n_sources: int, timeout_s: float):
    """Cold start, RSS, HTTP queries with/without a prior, warm restart."""
    from monoloc.core.geometry import planar_from_T_world_from_cam
    from monoloc.core.prior import RetrievalPrior

    def expected(tile, q):
        return planar_from_T_world_from_cam(tile.T_world_from_source @ q.T_world_from_cam)[:2]

    own = [expected(tiles[q.source], q) for q in queries]
    copy_tiles = [tiles[n_sources + q.source] for q in queries]  # turned, perturbed copies
    on_copy = [expected(t, q) for t, q in zip(copy_tiles, queries, strict=True)]
    every_copy = [
        np.array([expected(t, q) for t in tiles if t.source == q.source]) for q in queries
    ]
    index_dir = settings.index_dir
    shutil.rmtree(index_dir, ignore_errors=True)
    out: dict = {}
    with served(settings, queries[0], map_id, timeout_s) as (client, pid, cold_s):
        out["cold_start_s"] = cold_s
        out["rss_kb"] = status_kb(pid)
        priors = [RetrievalPrior(x, y, PRIOR_RADIUS_M) for x, y in own]
        out["prior_own_tile"] = http_queries(client, map_id, queries, priors, own)
        priors = [RetrievalPrior(x, y, PRIOR_RADIUS_M) for x, y in on_copy]
        out["prior_turned_copy"] = http_queries(client, map_id, queries, priors, on_copy)
        free = http_queries(client, map_id, queries, [None] * len(queries), own)
        # without a prior any copy of the place is a right answer
        hits = []
        for q, places in zip(queries, every_copy, strict=True):
            best = client.localize(map_id, q.png, seed=1, retries=0).best_pose_world
            hits.append(np.all(np.isfinite(best)) and np.min(np.hypot(*(places - best[:2]).T)) < 1)
        free["within_1m"] = float(np.mean(hits))
        out["no_prior"] = free
        out["rss_kb_after_queries"] = status_kb(pid)
    with served(settings, queries[0], map_id, timeout_s) as (_, pid, warm_s):
        out["warm_restart_s"] = warm_s
        out["rss_kb_warm"] = status_kb(pid)
    return out


# ---- the run ---------------------------------------------------------------------------------
def measure_size(settings, size_of, factory, plan, queries, work: Path, timeout_s, rebuild_max):
    from monoloc.core.geometry import planar_from_T_world_from_cam
    from monoloc.core.prior import RetrievalPrior

    own = [
        planar_from_T_world_from_cam(plan.tiles[q.source].T_world_from_source @ q.T_world_from_cam)
        for q in queries
    ]
    priors = [RetrievalPrior(p[0], p[1], PRIOR_RADIUS_M) for p in own]
    figures = dict(disk_bytes=size_of())
    print(f"  disk {figures['disk_bytes'] / 1e9:.2f} GB (load {load()})", flush=True)
    n_sources = len(plan.sources)
    figures["server"] = server_figures(
        settings, plan.dest.id, queries, plan.tiles, n_sources, timeout_s
    )
    print(f"  server {figures['server']} (load {load()})", flush=True)
    rebuild = len(plan.rows) <= rebuild_max
    figures["index"] = index_figures(
        settings, factory, plan.dest.id, queries, priors, work, rebuild
    )
    print(f"  index {figures['index']} (load {load()})", flush=True)
    return figures


def run(args) -> dict:
    from monoloc.server.ingest.bulk import TileConfig, prepare_tiling, write_tiles
    from monoloc.server.ingest.manage import create_map
    from monoloc.server.storage import maps as maps_repo
    from monoloc.server.storage.db import create_engine_for, make_session_factory, session_scope
    from monoloc.server.storage.migrate import upgrade_database
    from monoloc.server.vision.vocabulary import Vocabulary

    work = args.work_dir.resolve()
    work.mkdir(parents=True, exist_ok=True)
    seeds = [int(s) for s in args.seeds.split(",")]
    result = dict(
        sizes_measured=args.sizes,
        database=args.database,
        commit=args.commit or git("rev-parse", "HEAD"),
        index_commit=args.commit or git("log", "-1", "--format=%H", "--", "server/index"),
        machine=dict(cpus=os.cpu_count(), load_before=load()),
        seeds=seeds,
        base_frames=args.base_frames,
    )
    roots = render_base(work, seeds, args.base_frames)
    with database(args.database, work, args.reuse) as (settings, size_of):
        upgrade_database(settings.database_url)
        engine = create_engine_for(settings)
        factory = make_session_factory(engine)
        from monoloc.server.ingest.sources import read_kitti_sequence

        if args.reuse:
            result["pipeline_ingest"] = None  # measured by the run that made the database
        else:
            result["pipeline_ingest"] = ingest_base(factory, roots, seeds)
            print(f"pipeline ingest {result['pipeline_ingest']} (load {load()})", flush=True)
            create_map(factory, "scale", read_kitti_sequence(roots[0], "00").intrinsics)
        with session_scope(factory) as session:
            record = maps_repo.get_map_by_name(session, "scale")
            vocab = maps_repo.get_vocabulary(session, record.vocabulary_id)
        vocabulary = Vocabulary.from_centres(np.asarray(vocab.centres), vocab.description)
        queries = query_frames(roots, args.queries_per_city, vocabulary)
        sources = [f"city-{s}" for s in seeds]
        result["sizes"] = {}
        for size in args.sizes:
            plan = prepare_tiling(factory, "scale", sources, TileConfig(entries=size))
            print(f"tiling to {size} entries ({len(plan.tiles)} tiles)", flush=True)
            summary = write_tiles(factory, plan)
            figures = dict(
                bulk_added=summary.entries_added,
                bulk_s=summary.seconds,
                bulk_entries_per_s=summary.entries_per_s,
                tiles=summary.tiles,
                load=load(),
            )
            print(f"  bulk {figures}", flush=True)
            figures |= measure_size(
                settings, size_of, factory, plan, queries, work, args.timeout_s, args.rebuild_max
            )
            result["sizes"][str(size)] = figures
            result["scaling"] = scaling(result)
            args.out.write_text(json.dumps(result, indent=2) + "\n")  # what is done so far
        engine.dispose()
    result["machine"]["load_after"] = load()
    if not args.keep:
        shutil.rmtree(work / f"data-{args.database}", ignore_errors=True)
        shutil.rmtree(work / "bench-index", ignore_errors=True)
    return result


def _figures(f: dict, size: int) -> dict[str, float]:
    s = f["server"]
    return {
        "disk_bytes_per_entry": f["disk_bytes"] / size,
        "rss_anon_mb": s["rss_kb"]["RssAnon"] / 1024,
        "rss_file_mb": s["rss_kb"]["RssFile"] / 1024,
        "cold_start_s": s["cold_start_s"],
        "warm_restart_s": s["warm_restart_s"],
        "rebuild_s": f["index"]["rebuild_s"],
        "bulk_entries_per_s": f["bulk_entries_per_s"],
        "p50_ms_prior": s["prior_own_tile"]["p50_ms"],
        "p99_ms_prior": s["prior_own_tile"]["p99_ms"],
        "p50_ms_prior_copy": s["prior_turned_copy"]["p50_ms"],
        "p99_ms_prior_copy": s["prior_turned_copy"]["p99_ms"],
        "p50_ms_no_prior": s["no_prior"]["p50_ms"],
        "p99_ms_no_prior": s["no_prior"]["p99_ms"],
        "within_1m_prior": s["prior_own_tile"]["within_1m"],
        "within_1m_prior_copy": s["prior_turned_copy"]["within_1m"],
        "within_1m_no_prior_any_copy": s["no_prior"]["within_1m"],
        "recall_at_10": f["index"]["recall_at_10"],
        "recall_at_10_prior": f["index"]["recall_at_10_prior"],
        "distance_ratio_at_10_mean": f["index"].get("distance_ratio_at_10_mean"),
    }


def scaling(result: dict) -> dict:
    """Each figure at every measured size; the first size is the baseline."""
    sizes = [int(n) for n in result["sizes"]]
    table = {str(n): _figures(result["sizes"][str(n)], n) for n in sizes}
    if len(sizes) > 1:
        a, b = sizes[0], sizes[-1]
        grew = result["sizes"][str(b)]["disk_bytes"] - result["sizes"][str(a)]["disk_bytes"]
        table["disk_bytes_per_added_entry"] = grew / (b - a)
    return table


def print_table(result: dict) -> None:
    sizes = [n for n in result["sizes"]]
    print(
        f"\n{result['database']}: sizes {', '.join(sizes)} in one run, the first the baseline "
        f"(load before {result['machine']['load_before']}, after {result['machine']['load_after']})"
    )
    print(f"{'figure':30s}" + "".join(f"{n:>12s}" for n in sizes) + "   last/first")
    table = result["scaling"]
    for key in table[sizes[0]]:
        values = [table[n][key] for n in sizes]
        known = values[0] is not None and values[-1] is not None and values[0] != 0
        ratio = f"{values[-1] / values[0]:6.2f}x" if known else "     -"
        cells = "".join(f"{v:12.3f}" if v is not None else f"{'-':>12s}" for v in values)
        print(f"{key:30s}{cells}   {ratio}")
    if "disk_bytes_per_added_entry" in table:
        print(f"disk per added entry: {table['disk_bytes_per_added_entry']:.0f} B")
    ingest = result["pipeline_ingest"]
    if ingest is None:
        return
    print(
        f"real pipeline on the base: {ingest['entries']} entries from {ingest['frames']} "
        f"frames, {ingest['entries_per_s']:.1f} entries/s"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--entries", type=int, default=100_000, help="the last size")
    parser.add_argument(
        "--sizes", default="20000", help="sizes measured before --entries (the first: baseline)"
    )
    parser.add_argument("--database", choices=("sqlite", "postgresql"), default="sqlite")
    parser.add_argument("--work-dir", type=Path, default=Path("/tmp/monoloc-scale"))
    parser.add_argument("--seeds", default="21,22", help="sim cities of the base")
    parser.add_argument("--base-frames", type=int, default=600, help="map/query frames per city")
    parser.add_argument("--queries-per-city", type=int, default=12)
    parser.add_argument("--timeout-s", type=float, default=3600.0, help="per server start")
    parser.add_argument("--keep", action="store_true", help="keep the database")
    parser.add_argument(
        "--reuse", action="store_true", help="SQLite: go on with the database a run left"
    )
    parser.add_argument(
        "--rebuild-max",
        type=int,
        default=200_000,
        help="above this size the index is not rebuilt in this process (the cold start does)",
    )
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument(
        "--commit", default="", help="the commit this code is (when run from an exported copy)"
    )
    args = parser.parse_args()
    args.sizes = [int(n) for n in args.sizes.split(",") if n] + [args.entries]
    if args.sizes != sorted(set(args.sizes)):
        parser.error("--sizes must grow and stay below --entries")
    args.out = args.out or RESULTS / f"scale_{args.database}_{args.entries}.json"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    result = run(args)
    result["scaling"] = scaling(result)
    print_table(result)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

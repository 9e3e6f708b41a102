"""What one map entry costs a replica (memory) and the database (storage), measured.

* **Index memory per entry**, the product beside the lab baseline, each in a fresh
  process: the growth of its anonymous resident memory (``RssAnon``: the replica's own)
  and of its file-backed resident memory (``RssFile``: mapped files; the product reads its
  float VLAD file with ``pread``, so the rows it reads sit in the page cache, which the
  kernel reclaims as it needs, not in the process), divided by the entry count.
  - product: a writer process builds the index files from ``--entries`` synthetic unit
    VLADs the way a replica rebuilds a map (``persist.rebuild_index``); a reader process
    loads them as a replica starts (``load_index``) and then runs ``--queries`` searches
    (each reads k + 20 float VLADs from the file);
  - baseline (``--baseline-max``, the index of 2026-12-01: bench/lab/float_index.py): the
    entries added to a float-resident index, as this bench measured it until then.
* **Entry cache per entry**: descriptors + 3D points + pose of real entries (the cache
  holds up to 20,000 by default), and **database bytes per entry**: the stored blobs
  of real entries, read from a database built by bench/load.py (``out/bench_load``) or
  given with ``--database-url`` (skipped when there is none).

Writes bench/results/footprint.json. Usage:
    python -m bench.footprint [--entries 200000,1000000] [--baseline-max 200000]
        [--database-url sqlite:///...]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).parent / "results"
DEFAULT_DB = ROOT / "out" / "bench_load" / "data-1" / "monoloc.db"
BATCH = 10_000


def rss_bytes() -> dict[str, int]:
    """This process's resident memory: anonymous (its own) and file-backed (mapped page
    cache), bytes."""
    out = {}
    for line in Path("/proc/self/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("RssAnon", "RssFile"):
            out[key] = int(value.split()[0]) * 1024
    if len(out) != 2:
        raise RuntimeError("no RssAnon / RssFile in /proc/self/status")
    return out


def synthetic_batches(n: int, seed: int = 0):
    """``MapVectors`` batches of n random unit VLADs, their sign codes and poses."""
    from monoloc.server.storage.records import MapVectors
    from monoloc.server.vision.binary_code import vlad_binary_code

    rng = np.random.default_rng(seed)
    for start in range(0, n, BATCH):
        m = min(BATCH, n - start)
        vlads = rng.normal(size=(m, 2048)).astype(np.float32)
        vlads /= np.linalg.norm(vlads, axis=1, keepdims=True)
        poses = rng.uniform(-1000, 1000, size=(m, 3))
        ids = np.arange(start, start + m, dtype=np.int64)
        yield MapVectors(ids, vlads, vlad_binary_code(vlads), poses)


def _write_files(n: int, path: Path) -> dict:
    from monoloc.server.index.persist import rebuild_index

    start = time.perf_counter()
    rebuild_index(path, synthetic_batches(n), 1)
    return {"build_s": time.perf_counter() - start}


def _read_product(n: int, path: Path, queries: int) -> dict:
    from monoloc.server.index.persist import load_index
    from monoloc.server.index.warmup import warm_up
    from monoloc.server.vision.binary_code import vlad_binary_code

    warm_up()  # kernels and FAISS loaded before the baseline reading
    before = rss_bytes()
    start = time.perf_counter()
    index = load_index(path, 1)
    load_s = time.perf_counter() - start
    loaded = rss_bytes()
    rng = np.random.default_rng(1)
    for _ in range(queries):
        q = rng.normal(size=2048).astype(np.float32)
        q /= np.linalg.norm(q)
        index.search(q, vlad_binary_code(q), k=10)
    searched = rss_bytes()
    assert len(index) == n
    return {
        "load_s": load_s,
        "anon_bytes_per_entry": (loaded["RssAnon"] - before["RssAnon"]) / n,
        "file_bytes_per_entry_after_load": (loaded["RssFile"] - before["RssFile"]) / n,
        "anon_bytes_per_entry_after_queries": (searched["RssAnon"] - before["RssAnon"]) / n,
        "file_bytes_per_entry_after_queries": (searched["RssFile"] - before["RssFile"]) / n,
        "queries": queries,
        "disk_bytes_per_entry": sum(p.stat().st_size for p in path.parent.iterdir()) / n,
    }


def _read_baseline(n: int) -> dict:
    from bench.lab.float_index import FloatRetrievalIndex
    from monoloc.server.index.warmup import warm_up

    warm_up()
    index = FloatRetrievalIndex()
    before = rss_bytes()
    for batch in synthetic_batches(n):
        index.add(batch.entry_ids, batch.codes, batch.vlads, batch.planar)
    grown = rss_bytes()
    return {
        "anon_bytes_per_entry": (grown["RssAnon"] - before["RssAnon"]) / n,
        "file_bytes_per_entry_after_load": (grown["RssFile"] - before["RssFile"]) / n,
    }


def _child(role: str, n: int, path: Path, queries: int) -> dict:
    """Run one measurement in a fresh process (its resident memory is the index's alone)."""
    cmd = [sys.executable, "-m", "bench.footprint", "--child", role, "--entries", str(n)]
    cmd += ["--path", str(path), "--queries", str(queries)]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=3600)
    if done.returncode != 0:
        raise RuntimeError(f"{role} at {n} entries failed: {done.stderr.strip()[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def index_footprint(n: int, queries: int, baseline: bool) -> dict:
    with tempfile.TemporaryDirectory(dir=ROOT / "out") as tmp:
        path = Path(tmp) / "map_1.index.npz"
        row = {"entries": n, "loadavg_before": os.getloadavg()[0]}
        row["product"] = _child("write", n, path, 0) | _child("read", n, path, queries)
    if baseline:
        row["baseline_2026_12_01"] = _child("baseline", n, path, 0)
    row["loadavg_after"] = os.getloadavg()[0]
    return row


# What a product index holds per entry in its arrays: id 8, code 256, 4-bit VLAD 1024,
# sketch 32, pose 24, VLAD ref 8, sorted id and its row 16, the planar grid (cell key and
# row, monoloc.server.index.grid) 16.
ARRAYS_BYTES_PER_ENTRY = 8 + 256 + 1024 + 32 + 24 + 8 + 16 + 16


def index_summary(rows: list[dict]) -> dict:
    """footprint.json's index part: the first size's product figure as ``index`` (the
    keys bench/report.py reads) and every size under ``index_sizes``."""
    first = rows[0]
    return {
        "index": {
            "entries": first["entries"],
            "rss_bytes_per_entry": first["product"]["anon_bytes_per_entry"],
            "arrays_bytes_per_entry": ARRAYS_BYTES_PER_ENTRY,
        },
        "index_sizes": rows,
    }


def stored_bytes_per_entry(url: str) -> dict:
    from sqlalchemy import create_engine, func, select

    from monoloc.server.storage.models import Entry

    engine = create_engine(url)
    blobs = (
        Entry.vlad,
        Entry.code,
        Entry.keypoints_px,
        Entry.descriptors,
        Entry.points_cam,
        Entry.T_world_from_cam,
    )
    with engine.connect() as connection:
        n = connection.execute(select(func.count(Entry.id))).scalar_one()
        sums = connection.execute(select(*(func.sum(func.length(b)) for b in blobs))).one()
        points = connection.execute(select(func.avg(Entry.n_points))).scalar_one()
    engine.dispose()
    sizes = {b.key: int(s or 0) / max(1, n) for b, s in zip(blobs, sums, strict=True)}
    out = {
        "entries": int(n),
        "mean_points": float(points or 0),
        "blob_bytes_per_entry": sizes,
        "blob_bytes_total_per_entry": sum(sizes.values()),
        "cache_bytes_per_entry": sizes["descriptors"] + sizes["points_cam"] + 128,
    }
    if url.startswith("sqlite:///"):
        path = Path(url.removeprefix("sqlite:///"))
        out["sqlite_file_bytes_per_entry"] = path.stat().st_size / max(1, n)
    return out


def _print_index(row: dict) -> None:
    p, n = row["product"], row["entries"]
    print(
        f"index at {n} entries: product {p['anon_bytes_per_entry']:.0f} B/entry anonymous "
        f"after load, {p['anon_bytes_per_entry_after_queries']:.0f} after {p['queries']} "
        f"queries; file-backed {p['file_bytes_per_entry_after_load']:.0f} / "
        f"{p['file_bytes_per_entry_after_queries']:.0f} B/entry; "
        f"disk {p['disk_bytes_per_entry']:.0f} B/entry; load {p['load_s']:.1f} s "
        f"(load average {row['loadavg_before']:.1f})"
    )
    base = row.get("baseline_2026_12_01")
    if base:
        print(
            f"{'':>10}baseline (float-resident, 2026-12-01) {base['anon_bytes_per_entry']:.0f} "
            f"B/entry anonymous, {base['file_bytes_per_entry_after_load']:.0f} file-backed"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--entries", default="200000,1000000")
    parser.add_argument("--baseline-max", type=int, default=200_000)
    parser.add_argument("--queries", type=int, default=200)
    parser.add_argument("--database-url", default=f"sqlite:///{DEFAULT_DB}")
    parser.add_argument("--child", choices=("write", "read", "baseline"), help=argparse.SUPPRESS)
    parser.add_argument("--path", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        n = int(args.entries)
        if args.child == "write":
            out = _write_files(n, args.path)
        elif args.child == "read":
            out = _read_product(n, args.path, args.queries)
        else:
            out = _read_baseline(n)
        print(json.dumps(out))
        return
    sizes = [int(s) for s in args.entries.split(",")]
    (ROOT / "out").mkdir(exist_ok=True)
    rows = []
    for n in sizes:
        rows.append(index_footprint(n, args.queries, n <= args.baseline_max))
        _print_index(rows[-1])
    print("goal: <= 2048 B/entry resident (issue 52)")
    result = index_summary(rows)
    url = args.database_url
    if not url.startswith("sqlite:///") or Path(url.removeprefix("sqlite:///")).exists():
        stored = stored_bytes_per_entry(url)
        result["stored"] = stored
        print(
            f"database: {stored['blob_bytes_total_per_entry']:.0f} B/entry of blobs "
            f"({stored['mean_points']:.0f} points/entry, {stored['entries']} entries); entry "
            f"cache {stored['cache_bytes_per_entry']:.0f} B/entry"
            + (
                f"; SQLite file {stored['sqlite_file_bytes_per_entry']:.0f} B/entry"
                if "sqlite_file_bytes_per_entry" in stored
                else ""
            )
        )
    else:
        print(f"database: {url} not found (bench/load.py builds it); not measured")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "footprint.json").write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()

"""What one map entry costs a replica (memory) and the database (storage), measured.

* **Index memory per entry**: the resident-memory growth of this process while a
  ``RetrievalIndex`` (the replica's in-memory index: float VLAD, binary code, sketch,
  planar pose, id maps, FAISS) takes ``--entries`` synthetic unit VLADs, divided by the
  count; beside it the bare arrays' size (2048 x 4 + 256 + 32 + 24 + 8 bytes).
* **Entry cache per entry**: descriptors + 3D points + pose of real entries (the cache
  holds up to 20,000 by default), and **database bytes per entry**: the stored blobs
  of real entries, read from a database built by bench/load.py (``out/bench_load``) or
  given with ``--database-url``; the database's own file size per entry for SQLite.

Writes bench/results/footprint.json. Usage:
    python -m bench.footprint [--entries 200000] [--database-url sqlite:///...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).parent / "results"
DEFAULT_DB = ROOT / "out" / "bench_load" / "data-1" / "monoloc.db"


def rss_bytes() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def index_bytes_per_entry(n: int, rng: np.random.Generator) -> dict:
    from monoloc.server.index.retrieval import RetrievalIndex
    from monoloc.server.vision.binary_code import vlad_binary_code

    index = RetrievalIndex()
    before = rss_bytes()
    batch = 10_000
    for start in range(0, n, batch):
        m = min(batch, n - start)
        vlads = rng.normal(size=(m, 2048)).astype(np.float32)
        vlads /= np.linalg.norm(vlads, axis=1, keepdims=True)
        codes = vlad_binary_code(vlads)
        poses = rng.uniform(-1000, 1000, size=(m, 3))
        index.add(np.arange(start, start + m, dtype=np.int64), codes, vlads, poses)
    grown = rss_bytes() - before
    return {
        "entries": n,
        "rss_bytes_per_entry": grown / n,
        "arrays_bytes_per_entry": 2048 * 4 + 256 + 32 + 24 + 8,
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--entries", type=int, default=200_000)
    parser.add_argument("--database-url", default=f"sqlite:///{DEFAULT_DB}")
    args = parser.parse_args()
    index = index_bytes_per_entry(args.entries, np.random.default_rng(0))
    print(
        f"index: {index['rss_bytes_per_entry']:.0f} B/entry resident at {args.entries} entries "
        f"(bare arrays {index['arrays_bytes_per_entry']} B)"
    )
    stored = stored_bytes_per_entry(args.database_url)
    print(
        f"database: {stored['blob_bytes_total_per_entry']:.0f} B/entry of blobs "
        f"({stored['mean_points']:.0f} points/entry, {stored['entries']} entries); entry cache "
        f"{stored['cache_bytes_per_entry']:.0f} B/entry"
        + (
            f"; SQLite file {stored['sqlite_file_bytes_per_entry']:.0f} B/entry"
            if "sqlite_file_bytes_per_entry" in stored
            else ""
        )
    )
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "footprint.json").write_text(
        json.dumps({"index": index, "stored": stored}, indent=2)
    )


if __name__ == "__main__":
    main()

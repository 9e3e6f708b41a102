"""Retrieval at scale: 10k, 100k and 1M entries (goal at 1M: p50 <= 2 ms, recall@10 >= 0.95).

Real VLADs for a million images cannot be made here, so the map is a synthetic route
(see ``synthetic_route``): neighbouring places look alike, distant ones do not, and each
entry is a noisy view of its place. Queries are new noisy views of random entries. The
map is built as a replica rebuilds one (``persist.rebuild_index``: its float VLADs in
its file, read back row by row through the page cache). For every size it prints the
p50 / p99 search time on one core and recall@10 of the monoloc index (Hamming shortlist:
FAISS binary flat, from 50k entries the sketch scan and the full codes; then the 4-bit
VLADs; then exact float distances of the k + 20 nearest) without a prior and with
priors of 50 m and 2.5 km (200 and 10,000 entries inside), the same for the lab baseline
of 2026-12-01 (bench/lab/float_index.py: float VLADs resident, a prior's inside rows
re-ranked exactly; ``--float-baseline-max``), the product again with its float file
evicted from the page cache before each mode ("cold": every read goes to disk), the
exact float k-NN (brute force, the
paper-faithful search) and memory per entry, all in the same run. Recall is against
exact float search (inside the prior with one), computed by a separate process (the
timed process never maps the float file while the product is timed: a mapping would
hold it in the page cache and in the process, and the "cold" eviction could not evict
it). ``--baselines hnsw,ivf`` also times
FAISS's binary HNSW and IVF shortlists (with the settings they had as index kinds,
re-ranked exactly), the graph and inverted index the sketch scan was chosen over;
building HNSW over 1M entries takes a long while, so they are off by default.
Usage: python -m bench.retrieval [--sizes 10000,100000,1000000] [--queries 100]
[--float-baseline-max 1000000] [--baselines hnsw,ivf]"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from monoloc.server.index.retrieval import SearchResult
from monoloc.server.vision.binary_code import vlad_binary_code

RESULTS = Path(__file__).parent / "results"
DIM = 2048
BASELINES = ("hnsw", "ivf")


def synthetic_route(n: int, rng: np.random.Generator, chunk: int = 50_000) -> np.ndarray:
    """(n, 2048) float16 unit vectors along a route (float16 halves the bench's memory).

    Place prototypes follow an AR(1) process, p_i = a p_(i-1) + sqrt(1 - a^2) w_i with
    a = 0.9, so neighbouring entries look alike and entries a few dozen frames apart are
    unrelated, as on a long drive; each entry is its prototype plus view noise. (A plain
    random walk, the first model tried, made every entry of a 1M map a near-duplicate of
    thousands of others, which no real street does.)
    """
    a, view_noise = 0.9, 0.6
    out = np.empty((n, DIM), dtype=np.float16)
    proto = rng.normal(size=DIM).astype(np.float32)
    for start in range(0, n, chunk):
        m = min(chunk, n - start)
        fresh = rng.normal(size=(m, DIM)).astype(np.float32) * np.float32(np.sqrt(1 - a * a))
        protos = np.empty((m, DIM), dtype=np.float32)
        for i in range(m):
            proto = a * proto + fresh[i]
            protos[i] = proto
        views = protos + rng.normal(size=(m, DIM)).astype(np.float32) * np.float32(view_noise)
        views /= np.linalg.norm(views, axis=1, keepdims=True)
        out[start : start + m] = views
    return out


def exact_topk(vlads16: np.ndarray, queries: np.ndarray, k: int, chunk: int = 100_000):
    """Exact float L2 top-k over all entries (the baseline search), chunked."""
    best_d = np.full((len(queries), k), np.inf, dtype=np.float32)
    best_i = np.zeros((len(queries), k), dtype=np.int64)
    q_norm = (queries**2).sum(1)
    for start in range(0, len(vlads16), chunk):
        block = vlads16[start : start + chunk].astype(np.float32)
        d = q_norm[:, None] + (block**2).sum(1)[None, :] - 2.0 * queries @ block.T
        idx = np.argpartition(d, k, axis=1)[:, :k] if d.shape[1] > k else np.argsort(d, 1)
        cand_d = np.concatenate([best_d, np.take_along_axis(d, idx, 1)], axis=1)
        cand_i = np.concatenate([best_i, idx + start], axis=1)
        order = np.argsort(cand_d, axis=1)[:, :k]
        best_d = np.take_along_axis(cand_d, order, 1)
        best_i = np.take_along_axis(cand_i, order, 1)
    return best_i


class FaissShortlist:
    """Baseline: a FAISS binary index over the codes shortlists ``shortlist`` entries by
    Hamming distance, re-ranked by exact float distance; the search interface of
    :class:`RetrievalIndex` (entry ids are the rows)."""

    def __init__(self, index, vlads: np.ndarray, shortlist: int) -> None:
        self.index, self.vlads, self.shortlist = index, vlads, shortlist

    def search(self, vlad_query: np.ndarray, code_query: np.ndarray, k: int = 10) -> SearchResult:
        _, found = self.index.search(code_query.reshape(1, -1), max(self.shortlist, k))
        rows = found[0][found[0] >= 0]
        d = np.linalg.norm(self.vlads[rows].astype(np.float32) - vlad_query, axis=1)
        order = np.argsort(d, kind="stable")[:k]
        return SearchResult(rows[order], d[order].astype(np.float32))


def faiss_baseline(kind: str, codes: np.ndarray, vlads: np.ndarray) -> FaissShortlist:
    """HNSW (M 32, efConstruction 40, efSearch 128, shortlist 100) or IVF (nlist 2 sqrt(N),
    trained on 40 codes per list, nprobe 32, shortlist 400) over ``codes``."""
    import faiss

    if kind == "hnsw":
        index = faiss.IndexBinaryHNSW(DIM, 32)
        index.hnsw.efConstruction = 40
        index.hnsw.efSearch = 128
        shortlist = 100
    elif kind == "ivf":
        nlist = max(16, int(2.0 * math.sqrt(len(codes))))
        index = faiss.IndexBinaryIVF(faiss.IndexBinaryFlat(DIM), DIM, nlist)
        n_train = 40 * nlist
        index.train(codes if len(codes) <= n_train else codes[:: len(codes) // n_train])
        index.nprobe = 32
        shortlist = 400
    else:
        raise ValueError(f"unknown baseline {kind!r}; use one of {BASELINES}")
    index.add(codes)
    return FaissShortlist(index, vlads, shortlist)


def timed_searches(index, queries: np.ndarray, q_codes: np.ndarray, priors=None):
    """Per-query search times (ms) and found ids of ``index`` (anything with ``search``),
    after three warm-up searches; ``priors`` one per query (or None)."""
    priors = priors if priors is not None else [None] * len(queries)
    for q, c, p in zip(queries[:3], q_codes[:3], priors[:3], strict=True):
        _search(index, q, c, p)  # compile / warm the caches
    times, found = [], []
    for q, c, p in zip(queries, q_codes, priors, strict=True):
        t0 = time.perf_counter()
        res = _search(index, q, c, p)
        times.append((time.perf_counter() - t0) * 1e3)
        found.append(res.entry_ids)
    return times, found


def _search(index, q, c, prior):
    if prior is None:
        return index.search(q, c, k=10)
    return index.search(q, c, k=10, prior=prior)


def recall_at_10(truth: np.ndarray, found: list[np.ndarray]) -> float:
    hits = [len(set(t.tolist()) & set(f.tolist())) for t, f in zip(truth, found, strict=True)]
    return float(np.mean(hits)) / 10


def route_batches(n: int, rng: np.random.Generator, chunk: int = 50_000):
    """``MapVectors`` batches of :func:`synthetic_route` (float32), their sign codes and
    poses 0.5 m apart along x: the map a replica rebuilds, one batch at a time."""
    from monoloc.server.storage.records import MapVectors

    for start in range(0, n, chunk):
        m = min(chunk, n - start)
        vlads = synthetic_route(m, rng).astype(np.float32)
        vlads /= np.linalg.norm(vlads, axis=1, keepdims=True)
        poses = np.zeros((m, 3))
        poses[:, 0] = np.arange(start, start + m) * 0.5
        yield MapVectors(np.arange(start, start + m), vlads, vlad_binary_code(vlads), poses)


def resident_bytes_per_entry(index) -> float:
    """The arrays a product index keeps in memory per entry (its float VLADs are in the
    file), FAISS's copy of the codes in the flat kind included."""
    n = len(index)
    arrays = (index._ids, index._codes, index._compressed, index._poses, index._refs)
    held = sum(a[:n].nbytes for a in arrays) + 32 * n  # + the sketches
    held += index._sorted_ids.nbytes + index._sorted_rows.nbytes + index._grid.nbytes
    held += n * (256 + 8) if index._faiss is not None else 0
    return held / n


def baseline_bytes_per_entry(index) -> float:
    """The same for the float-resident baseline (its id dict about 100 B per entry)."""
    n = len(index)
    arrays = (index._ids, index._codes, index._vlads, index._poses)
    held = sum(a[:n].nbytes for a in arrays) + 32 * n + 100 * n
    held += n * (256 + 8) if index._faiss is not None else 0
    return held / n


PRIOR_RADII_M = (50.0, 2500.0)  # 200 and 10,000 entries inside at 0.5 m spacing


def _priors(picks: np.ndarray, radius_m: float | None):
    from monoloc.core.prior import RetrievalPrior

    if radius_m is None:
        return [None] * len(picks)
    return [RetrievalPrior(x_m=0.5 * float(i), y_m=0.0, radius_m=radius_m) for i in picks]


def prior_truth(vlads: np.ndarray, queries: np.ndarray, picks: np.ndarray, radius_m: float):
    """Exact top-10 ids inside each query's prior (entries within radius_m of its pick)."""
    out = []
    for q, i in zip(queries, picks, strict=True):
        lo = max(0, int(np.ceil(i - 2 * radius_m)))
        hi = min(len(vlads), int(np.floor(i + 2 * radius_m)) + 1)
        d = np.linalg.norm(vlads[lo:hi].astype(np.float32) - q, axis=1)
        out.append(lo + np.argsort(d, kind="stable")[:10])
    return np.array(out)


def truths_of(vlad_path: Path, queries: np.ndarray, picks: np.ndarray, work: Path):
    """The exact top-10 without a prior and inside each of PRIOR_RADII_M, and the brute
    force's ms per query, from a child process (see the module's docstring)."""
    np.save(work / "queries.npy", queries)
    np.save(work / "picks.npy", picks)
    cmd = [sys.executable, "-m", "bench.retrieval", "--truth-of", str(vlad_path), str(work)]
    subprocess.run(cmd, cwd=RESULTS.parent.parent, check=True, timeout=7200)
    with np.load(work / "truths.npz") as data:
        truths = {name: data[name] for name in data.files if name != "exact_ms"}
        return truths, float(data["exact_ms"])


def _truth_child(vlad_path: Path, work: Path) -> None:
    """``--truth-of``: read the map's float file (mapped here, in this process only),
    write the truths and the brute force's time per query to work/truths.npz."""
    threadpool_limits(1)
    vlads = np.load(vlad_path, mmap_mode="r")
    queries, picks = np.load(work / "queries.npy"), np.load(work / "picks.npy")
    n_timed = min(20, len(queries))
    start = time.perf_counter()
    exact_topk(vlads, queries[:n_timed], 10)
    exact_ms = (time.perf_counter() - start) * 1e3 / n_timed
    truths = {"no_prior": exact_topk(vlads, queries, 10)}
    for radius_m in PRIOR_RADII_M:
        truths[f"prior_{radius_m:.0f}m"] = prior_truth(vlads, queries, picks, radius_m)
    np.savez(work / "truths.npz", exact_ms=np.array(exact_ms), **truths)


def drop_page_cache(path: Path) -> None:
    """Evict a file's clean pages from the page cache (this file's only)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(fd)


def timed_modes(index, queries, q_codes, picks, truths, cold_file: Path | None = None) -> dict:
    """p50 / p99 and recall@10 without a prior and with each of PRIOR_RADII_M; with
    ``cold_file``, that file leaves the page cache before each mode (the worst case: a
    replica whose page cache holds none of its float VLADs)."""
    out = {}
    for radius_m in (None, *PRIOR_RADII_M):
        name = "no_prior" if radius_m is None else f"prior_{radius_m:.0f}m"
        if cold_file is not None:
            drop_page_cache(cold_file)
        times, found = timed_searches(index, queries, q_codes, _priors(picks, radius_m))
        out[name] = {
            "p50_ms": float(np.median(times)),
            "p99_ms": float(np.percentile(times, 99)),
            "recall_at_10": recall_at_10(truths[name], found),
        }
    return out


def run_size(
    n: int,
    n_queries: int,
    rng: np.random.Generator,
    baselines: tuple[str, ...] = (),
    float_baseline: bool = True,
) -> dict:
    import faiss

    from bench.lab.float_index import FloatRetrievalIndex
    from monoloc.server.index.persist import rebuild_index, vlad_files

    with tempfile.TemporaryDirectory(dir=RESULTS.parent.parent / "out") as tmp:
        path = Path(tmp) / "map_1.index.npz"
        build_start = time.perf_counter()
        index = rebuild_index(path, route_batches(n, rng), 1)  # as a replica rebuilds
        build_s = time.perf_counter() - build_start
        vlad_path = vlad_files(path)[0]
        kind = index.kind
        picks = rng.choice(n, n_queries, replace=False)
        queries = index.vlads_at(picks) + rng.normal(size=(n_queries, DIM)).astype(np.float32) * (
            0.3 / np.sqrt(DIM)
        )
        queries /= np.linalg.norm(queries, axis=1, keepdims=True)
        q_codes = vlad_binary_code(queries)
        truths, baseline_ms = truths_of(vlad_path, queries, picks, Path(tmp))
        load_before = os.getloadavg()[0]
        modes = timed_modes(index, queries, q_codes, picks, truths)
        cold = timed_modes(index, queries, q_codes, picks, truths, vlad_path)
        row = {
            "entries": n,
            "index_kind": kind,
            "build_s": build_s,
            "p50_ms": modes["no_prior"]["p50_ms"],
            "p99_ms": modes["no_prior"]["p99_ms"],
            "recall_at_10": modes["no_prior"]["recall_at_10"],
            "modes": modes,
            "modes_cold_page_cache": cold,
            "baseline_exact_float_p50_ms": baseline_ms,
            "memory_bytes_per_entry": resident_bytes_per_entry(index),
            "loadavg_before": load_before,
            "loadavg": os.getloadavg()[0],
            "baselines": {},
        }
        # The baseline's codes and sketches are the product's: not recomputed.
        codes, sketches = index._codes[:n].copy(), index._sketches.rows(n)
        del index
        # The product timed, the float file is mapped to build the baselines, which copy
        # the VLADs they hold; unmapped before the float baseline is timed.
        if float_baseline:  # the float-resident index of 2026-12-01, same map and queries
            start = time.perf_counter()
            vlads = np.load(vlad_path, mmap_mode="r")
            baseline = FloatRetrievalIndex.from_arrays(
                np.arange(n),
                codes,
                vlads,
                np.c_[np.arange(n) * 0.5, np.zeros((n, 2))],
                sketches=sketches,
            )
            del vlads
            built_s, load_before = time.perf_counter() - start, os.getloadavg()[0]
            row["float_baseline"] = {
                "build_s": built_s,
                "memory_bytes_per_entry": baseline_bytes_per_entry(baseline),
                "modes": timed_modes(baseline, queries, q_codes, picks, truths),
                "loadavg_before": load_before,
                "loadavg": os.getloadavg()[0],
            }
            # Issue 52's "p99 with a prior <= 2x today's": the product's p99 over the
            # float baseline's, per prior.
            row["prior_p99_over_float_baseline"] = {
                name: modes[name]["p99_ms"] / row["float_baseline"]["modes"][name]["p99_ms"]
                for name in modes
                if name != "no_prior"
            }
            del baseline
        vlads = np.load(vlad_path, mmap_mode="r") if baselines else None
        for name in baselines:
            start = time.perf_counter()
            faiss.omp_set_num_threads(2)
            shortlist = faiss_baseline(name, codes, vlads)
            faiss.omp_set_num_threads(1)
            built_s = time.perf_counter() - start
            times, found = timed_searches(shortlist, queries, q_codes)
            row["baselines"][name] = {
                "build_s": built_s,
                "p50_ms": float(np.median(times)),
                "p99_ms": float(np.percentile(times, 99)),
                "recall_at_10": recall_at_10(truths["no_prior"], found),
            }
            del shortlist
        del vlads
    return row


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--sizes", default="10000,100000,1000000")
    parser.add_argument("--queries", type=int, default=100)
    parser.add_argument(
        "--baselines", default="", help=f"comma-separated, of {', '.join(BASELINES)}"
    )
    parser.add_argument(
        "--float-baseline-max",
        type=int,
        default=1_000_000,
        help="largest size at which the float-resident index of 2026-12-01 is measured too",
    )
    parser.add_argument("--truth-of", nargs=2, type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.truth_of:
        _truth_child(*args.truth_of)
        return
    baselines = tuple(b for b in args.baselines.split(",") if b)
    unknown = set(baselines) - set(BASELINES)
    if unknown:
        parser.error(f"unknown baselines {sorted(unknown)}; use {', '.join(BASELINES)}")
    import faiss

    faiss.omp_set_num_threads(1)
    threadpool_limits(1)  # one core, as the server runs each search
    rng = np.random.default_rng(0)
    rows = []
    print(f"load average {os.getloadavg()[0]:.1f} before; one search thread")
    print(
        f"{'entries':>9} {'index':>18} {'mode':>11} {'p50 ms':>8} {'p99 ms':>8} "
        f"{'recall@10':>9} {'B/entry':>8}"
    )
    for n in [int(s) for s in args.sizes.split(",")]:
        row = run_size(n, args.queries, rng, baselines, n <= args.float_baseline_max)
        rows.append(row)
        designs = [(f"product ({row['index_kind']})", row)]
        designs.append(("product, cold", {**row, "modes": row["modes_cold_page_cache"]}))
        if "float_baseline" in row:
            designs.append(("float 2026-12-01", row["float_baseline"]))
        for label, design in designs:
            for mode, m in design["modes"].items():
                print(
                    f"{n:>9} {label:>18} {mode:>11} {m['p50_ms']:>8.3f} {m['p99_ms']:>8.3f} "
                    f"{m['recall_at_10']:>9.3f} {design['memory_bytes_per_entry']:>8.0f}"
                )
        print(
            f"{n:>9} {'exact float k-NN':>18} {'no_prior':>11} "
            f"{row['baseline_exact_float_p50_ms']:>8.2f}   (brute force, load average "
            f"{row['loadavg']:.1f})"
        )
        for name, ratio in row.get("prior_p99_over_float_baseline", {}).items():
            print(
                f"{n:>9} p99 {name} over the float baseline's: {ratio:.2f}x (goal <= 2x; "
                f"load average {row['loadavg_before']:.1f}-{row['loadavg']:.1f} product, "
                f"{row['float_baseline']['loadavg_before']:.1f}-"
                f"{row['float_baseline']['loadavg']:.1f} baseline)"
            )
        for name, b in row["baselines"].items():
            print(
                f"{n:>9} {name:>18} {'no_prior':>11} {b['p50_ms']:>8.3f} {b['p99_ms']:>8.3f} "
                f"{b['recall_at_10']:>9.3f}   (baseline, built in {b['build_s']:.1f} s)"
            )
    print("goal at 1M entries: p50 <= 2 ms and recall@10 >= 0.95")
    last = rows[-1]
    if last["entries"] >= 1_000_000:
        met = last["p50_ms"] <= 2.0 and last["recall_at_10"] >= 0.95
        print(f"at 1M, one core: {'met' if met else 'MISSED'}")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "retrieval.json").write_text(
        json.dumps({"goal": {"p50_ms": 2.0, "recall_at_10": 0.95}, "sizes": rows}, indent=2) + "\n"
    )


if __name__ == "__main__":
    main()

"""End-to-end localization speed through the real server on localhost, beside the
paper-faithful pipeline.

`monoloc serve` runs as a subprocess on 127.0.0.1 (one uvicorn process; OpenCV, FAISS
and BLAS on one thread each; ``MONOLOC_WORKER_THREADS`` = 1 or 2 pipelines at a time).
The map is a sim city's map pass (1241 x 376, reused from ``out/bench_sim`` of
bench/localize.py, else generated into ``out/bench_speed/sim``), uploaded once through
the HTTP API and ingested by the server; the data directory is cached in
``out/bench_speed/data``. Each configuration then streams the query pass over the
WebSocket as fast as possible: every vehicle sends a frame, waits for its answer and
sends the next (what `monoloc drive` does), after a warm-up of ``WARMUP`` frames.
With 2 worker threads, 2 vehicles stream at once (one stream is served one frame at a
time, so a single vehicle cannot use the second thread).

Pipelines: ``monoloc`` (the product: binary-code shortlist + exact re-rank, Hamming
matching, guided PnP) and ``paper`` (``bench.lab.paper`` served by
``bench.lab.paper_server``: exact float k-NN over all VLADs, OpenCV brute-force matching,
independent PnP per entry); same features and VLAD.

Printed: server per-stage p50/p99 (the answers' ``timings_ms``), client round trip
p50/p99, end-to-end frames per second, the ratio to the paper pipeline, and the targets
(p50 <= 20 ms per query on one core; >= 5x the paper-faithful pipeline). Writes
bench/results/speed.json. Usage: python -m bench.speed [--frames 100] [--window 1]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import socket
import subprocess
import sys
import tarfile
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).parent / "results"
SHARED_SIM = ROOT / "out" / "bench_sim"
WORK = ROOT / "out" / "bench_speed"
ADMIN_KEY = "mlk_" + "B" * 43  # local benchmark data only
MAP_NAME = "bench_speed"
STAGES = ("decode", "features", "vlad", "retrieval", "lookup", "matching", "pnp", "total")
TARGET_P50_MS = 20.0
TARGET_SPEEDUP = 5.0
WARMUP = 10


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@contextmanager
def serve(data_dir: Path, pipeline: str, workers: int):
    """`monoloc serve` in a subprocess; yields its base URL once /readyz answers 200."""

    port = free_port()
    env = dict(
        os.environ,
        MONOLOC_BOOTSTRAP_ADMIN_KEY=ADMIN_KEY,
        MONOLOC_WORKER_THREADS=str(workers),
        MONOLOC_LOCALIZE_SEED="0",
        MONOLOC_CV_THREADS="1",
        MONOLOC_FAISS_THREADS="1",
    )
    # the paper's pipeline: the same server with the lab's stages (bench.lab.paper_server)
    module = "bench.lab.paper_server" if pipeline == "paper" else "monoloc.cli"
    cmd = [sys.executable, "-m", module, "serve", "--port", str(port)]
    cmd += ["--data-dir", str(data_dir), "--log-level", "warning"]
    proc = subprocess.Popen(cmd, env=env, cwd=ROOT)
    url = f"http://127.0.0.1:{port}"
    try:
        from monoloc.client.api import wait_until_ready

        wait_until_ready(url, 120.0, proc)
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def ensure_dataset(frames: int) -> Path:
    if (SHARED_SIM / "dataset.json").exists():
        return SHARED_SIM
    root = WORK / "sim"
    if not (root / "dataset.json").exists():
        from monoloc.sim.generate import GenerateConfig, generate_dataset

        print(f"generating {frames} + {frames} frames into {root} (once) ...", flush=True)
        generate_dataset(GenerateConfig(seed=0, runs=("map", "query"), max_frames=frames), root)
    return root


def ensure_map(dataset: Path) -> int:
    """The map run uploaded and ingested once; returns the map id (cached)."""
    from monoloc.client.api import MonolocClient

    marker, data_dir = WORK / "map.json", WORK / "data"
    if marker.exists():
        cached = json.loads(marker.read_text())
        if cached.get("dataset") == str(dataset) and data_dir.exists():
            return int(cached["map_id"])
    shutil.rmtree(data_dir, ignore_errors=True)
    data_dir.mkdir(parents=True)
    camera = json.loads((dataset / "dataset.json").read_text())["camera"]
    archive = WORK / "map_run.tar"
    with tarfile.open(archive, "w") as tar:  # plain tar: the images are PNG already
        tar.add(dataset / "sequences" / "00", arcname="kitti/sequences/00")
        tar.add(dataset / "poses" / "00.txt", arcname="kitti/poses/00.txt")
    print(f"uploading the map run ({archive.stat().st_size / 1e6:.0f} MB) ...", flush=True)
    with serve(data_dir, "monoloc", 2) as url, MonolocClient(url, ADMIN_KEY, 600.0) as client:
        made = client.request("POST", "/v1/maps", json={"name": MAP_NAME, "camera": camera})
        map_id = int(made.json()["id"])
        with open(archive, "rb") as fh:
            accepted = client.request(
                "POST",
                f"/v1/maps/{map_id}/runs",
                files={"archive": ("map.tar", fh, "application/x-tar")},
                data={"format": "kitti", "kind": "map"},
            ).json()
        while True:
            job = client.request("GET", f"/v1/jobs/{accepted['job']['id']}").json()
            if job["state"] in ("done", "failed", "interrupted"):
                break
            time.sleep(0.5)
        if job["state"] != "done":
            raise RuntimeError(f"ingestion failed: {job}")
    archive.unlink()
    marker.write_text(json.dumps({"map_id": map_id, "dataset": str(dataset)}))
    return map_id


def vehicle(url: str, map_id: int, frames: list[bytes], window: int, out: dict) -> None:
    """Stream ``frames`` with at most ``window`` unanswered; round trips in ms."""
    from monoloc.client.api import FrameStream

    sent: dict[int, float] = {}
    round_trip, answers = [], []
    with FrameStream(url, ADMIN_KEY, map_id, timeout_s=120.0) as stream:
        next_seq = 0
        for _ in range(len(frames)):
            while next_seq < len(frames) and next_seq - len(answers) < window:
                sent[next_seq] = time.perf_counter()
                stream.send(next_seq, 0.1 * next_seq, frames[next_seq])
                next_seq += 1
            answer = stream.receive()
            round_trip.append((time.perf_counter() - sent[answer["seq"]]) * 1e3)
            answers.append(answer)
    out["round_trip_ms"], out["answers"] = round_trip, answers


def measure(data_dir, map_id, frames, pipeline, workers, vehicles, window) -> dict:
    with serve(data_dir, pipeline, workers) as url:
        vehicle(url, map_id, frames[:WARMUP], 1, {})  # entry cache warm, as when running
        outs = [{} for _ in range(vehicles)]
        threads = [
            threading.Thread(target=vehicle, args=(url, map_id, frames, window, o)) for o in outs
        ]
        start = time.perf_counter()
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        wall = time.perf_counter() - start
    answers = [a for o in outs for a in o.get("answers", [])]
    if len(answers) != vehicles * len(frames):
        raise RuntimeError(f"{pipeline}/{workers}: a vehicle stream failed")
    processed = [a for a in answers if "timings_ms" in a]
    trips = [t for o in outs for t in o["round_trip_ms"]]

    def pct(values) -> dict[str, float]:
        return {
            "p50_ms": float(np.percentile(values, 50)),
            "p99_ms": float(np.percentile(values, 99)),
        }

    return {
        "pipeline": pipeline,
        "worker_threads": workers,
        "vehicles": vehicles,
        "window": window,
        "frames": len(answers),
        "dropped": sum(1 for a in answers if a.get("dropped")),
        "errors": sum(1 for a in answers if "error" in a),
        "share_with_hypotheses": float(np.mean([bool(a.get("hypotheses")) for a in processed])),
        "server": {s: pct([a["timings_ms"].get(s, 0.0) for a in processed]) for s in STAGES},
        "round_trip": pct(trips),
        "frames_per_s": len(answers) / wall,
        "wall_s": wall,
    }


def print_tables(runs: dict[str, dict], header: str) -> None:
    print(f"\n{header}")
    print(
        f"{'pipeline':<9}{'workers':>8}{'vehicles':>9}{'server p50':>12}{'p99':>8}"
        f"{'round trip p50':>16}{'p99':>8}{'frames/s':>10}{'hyps':>6}"
    )
    for r in runs.values():
        s, t = r["server"]["total"], r["round_trip"]
        hyps = 100 * r["share_with_hypotheses"]
        print(
            f"{r['pipeline']:<9}{r['worker_threads']:>8}{r['vehicles']:>9}"
            f"{s['p50_ms']:>10.1f}ms{s['p99_ms']:>6.1f}ms{t['p50_ms']:>14.1f}ms"
            f"{t['p99_ms']:>6.1f}ms{r['frames_per_s']:>10.1f}{hyps:>5.0f}%"
        )
    print("\nserver stages, one worker thread (p50 / p99 ms):")
    mono, paper = runs["monoloc_w1"]["server"], runs["paper_w1"]["server"]
    print(f"{'stage':<10}{'monoloc':>18}{'paper-faithful':>20}")
    for stage in STAGES:
        m, p = mono[stage], paper[stage]
        print(
            f"{stage:<10}{m['p50_ms']:>9.2f} / {m['p99_ms']:<6.1f}"
            f"{p['p50_ms']:>11.2f} / {p['p99_ms']:<6.1f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100, help="query frames per vehicle")
    parser.add_argument("--window", type=int, default=1, help="frames in flight per vehicle")
    args = parser.parse_args()

    from monoloc.client.replay import read_kitti_run

    WORK.mkdir(parents=True, exist_ok=True)
    dataset = ensure_dataset(args.frames)
    map_id = ensure_map(dataset)
    query = read_kitti_run(dataset, "01")
    frames = [p.read_bytes() for p in query.image_paths[: args.frames]]
    map_entries = len(list((dataset / "sequences" / "00" / "image_0").glob("*.png")))
    load_before = os.getloadavg()
    runs = {}
    for pipeline in ("monoloc", "paper"):
        for workers in (1, 2):
            name = f"{pipeline}_w{workers}"
            print(f"measuring {name} ...", flush=True)
            runs[name] = measure(
                WORK / "data", map_id, frames, pipeline, workers, workers, args.window
            )
    load_after = os.getloadavg()
    size = json.loads((dataset / "dataset.json").read_text())["camera"]
    print_tables(
        runs,
        f"end-to-end localization through `monoloc serve` on 127.0.0.1: {len(frames)} query "
        f"frames per vehicle, {size['width_px']}x{size['height_px']}, map of {map_entries} "
        f"entries, k=10, window {args.window}; load average before {load_before[0]:.2f}, "
        f"after {load_after[0]:.2f} ({os.cpu_count()} cores)",
    )
    mono, paper = runs["monoloc_w1"], runs["paper_w1"]
    speedup = {
        "server_p50": paper["server"]["total"]["p50_ms"] / mono["server"]["total"]["p50_ms"],
        "round_trip_p50": paper["round_trip"]["p50_ms"] / mono["round_trip"]["p50_ms"],
        "frames_per_s_w1": mono["frames_per_s"] / paper["frames_per_s"],
        "frames_per_s_w2": runs["monoloc_w2"]["frames_per_s"] / runs["paper_w2"]["frames_per_s"],
    }
    p50 = mono["server"]["total"]["p50_ms"]
    met = {"p50_one_core": p50 <= TARGET_P50_MS, "speedup": speedup["server_p50"] >= TARGET_SPEEDUP}
    print(
        f"\ntarget server p50 <= {TARGET_P50_MS:.0f} ms per query on one core: "
        f"{'met' if met['p50_one_core'] else 'NOT met'} ({p50:.1f} ms; paper-faithful "
        f"{paper['server']['total']['p50_ms']:.1f} ms; client round trip p50 "
        f"{mono['round_trip']['p50_ms']:.1f} ms)"
    )
    print(
        f"target >= {TARGET_SPEEDUP:.0f}x the paper-faithful pipeline: "
        f"{'met' if met['speedup'] else 'NOT met'} ({speedup['server_p50']:.2f}x server p50, "
        f"{speedup['round_trip_p50']:.2f}x round trip, {speedup['frames_per_s_w1']:.2f}x "
        f"frames/s with 1 worker, {speedup['frames_per_s_w2']:.2f}x with 2)"
    )
    RESULTS.mkdir(exist_ok=True)
    out = {
        "query_frames": len(frames),
        "map_entries": map_entries,
        "image": [size["width_px"], size["height_px"]],
        "k": 10,
        "window": args.window,
        "warmup_frames": WARMUP,
        "dataset": str(dataset.relative_to(ROOT) if dataset.is_relative_to(ROOT) else dataset),
        "load_average_before": load_before,
        "load_average_after": load_after,
        "cpu_count": os.cpu_count(),
        "machine": platform.platform(),
        "targets": {"p50_ms_one_core": TARGET_P50_MS, "speedup_vs_paper": TARGET_SPEEDUP},
        "runs": runs,
        "speedup_vs_paper": speedup,
        "target_met": met,
    }
    (RESULTS / "speed.json").write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {RESULTS / 'speed.json'}")


if __name__ == "__main__":
    main()

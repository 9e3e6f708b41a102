"""Crash trials: SIGKILL of a real server process during ingestion, entry adds and
deletes, and around the index file write (``bench.lab.crash_trials``), 50 trials by
default, kinds in turn, each on a fresh data directory with its own seed.

Figures: trials whose restart lost an acknowledged write, duplicated an entry, served
an index different from the database, or whose run counters did not add up (goal: 0 of
each), and the restart time after a SIGKILL. Baseline, from the same run: the start time
of the same server on a fresh directory (what a restart costs without recovery).
Data: a 16-frame KITTI-layout sim run (generated into out/bench_crash once).
Writes bench/results/crash.json.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from collections import Counter
from dataclasses import asdict
from pathlib import Path

RESULTS = Path(__file__).parent / "results"
DEFAULT_DATA = Path(__file__).parent.parent / "out" / "bench_crash"


def ensure_dataset(root: Path) -> Path:
    if (root / "dataset.json").exists():
        return root
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.lidar import LidarConfig

    generate_dataset(
        GenerateConfig(
            size="small",
            runs=("map",),
            max_frames=16,
            write_depth=False,
            lidar=LidarConfig(azimuth_steps=1000),
            seed=0,
        ),
        root,
    )
    return root


def _camera() -> dict:
    from monoloc.core.camera import KITTI_CAM0

    c = KITTI_CAM0
    return dict(fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy, width_px=c.width_px, height_px=c.height_px)


def _start_time_s(workdir: Path) -> float:
    from monoloc.local_server import free_port, new_admin_key, start_server, stop_server

    workdir.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    proc = start_server(workdir / "data", free_port(), new_admin_key(), workdir / "server.log")
    elapsed = time.monotonic() - start
    stop_server(proc)
    return elapsed


def main() -> None:
    import numpy as np

    from bench.lab.crash_trials import KINDS, TrialDataset, run_trial

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=50)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    args = parser.parse_args()
    dataset = TrialDataset(ensure_dataset(args.data), "00", _camera())
    results = []
    with tempfile.TemporaryDirectory(prefix="monoloc-crash-") as tmp:
        baseline_s = _start_time_s(Path(tmp) / "baseline")
        for i in range(args.trials):
            kind = KINDS[i % len(KINDS)]
            rng = np.random.default_rng(1000 + i)
            start = time.monotonic()
            result = run_trial(kind, dataset, Path(tmp) / f"trial-{i}", rng)
            status = "ok" if result.ok else "FAILED " + "; ".join(result.notes)
            print(
                f"trial {i + 1:2d}/{args.trials} {kind:11s} killed after "
                f"{result.killed_after_s:5.2f} s ({result.job_state_at_kill or '-'}), "
                f"{result.acknowledged} acknowledged, {time.monotonic() - start:5.1f} s: {status}",
                flush=True,
            )
            results.append(result)
    failures = Counter(
        name
        for r in results
        for name in ("lost", "duplicated", "index_mismatch", "counters_mismatch")
        if getattr(r, name)
    )
    restart = [r.restart_s for r in results if r.restart_s]
    summary = {
        "trials": len(results),
        "by_kind": dict(Counter(r.kind for r in results)),
        "trials_failed": sum(not r.ok for r in results),
        "failures": {
            k: failures.get(k, 0)
            for k in ("lost", "duplicated", "index_mismatch", "counters_mismatch")
        },
        "acknowledged_writes": sum(r.acknowledged for r in results),
        "restart_after_sigkill_s": {
            "p50": statistics.median(restart) if restart else None,
            "max": max(restart) if restart else None,
        },
        "baseline_fresh_start_s": baseline_s,
        "ingest_kills_by_job_state": dict(
            Counter(r.job_state_at_kill for r in results if r.kind != "entries")
        ),
        "results": [asdict(r) for r in results],
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "crash.json").write_text(json.dumps(summary, indent=2))
    print()
    print(
        f"{summary['trials']} SIGKILL trials {summary['by_kind']}: {summary['trials_failed']} "
        f"failed; lost / duplicated / index != database / counters: {summary['failures']} "
        f"(goal: 0); {summary['acknowledged_writes']} acknowledged writes checked"
    )
    print(
        f"restart after SIGKILL p50 {summary['restart_after_sigkill_s']['p50']:.1f} s, "
        f"max {summary['restart_after_sigkill_s']['max']:.1f} s; baseline fresh start "
        f"{baseline_s:.1f} s"
    )
    if summary["trials_failed"]:
        sys.exit(1)


if __name__ == "__main__":
    main()

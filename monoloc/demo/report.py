"""The demo's table and plots (degrees appear here, in human-facing output only)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rich.table import Table

from monoloc.client.drive import DriveResult
from monoloc.core.formats import kitti

PAPER_RMSE_M = 0.313


def summary_table(results: dict[str, DriveResult]) -> Table:
    table = Table(title="monoloc demo (sim city) vs the paper (KITTI 00)")
    table.add_column("", no_wrap=True)
    for name in results:
        table.add_column(name, justify="right")
    table.add_column("paper", justify="right", style="dim")

    def row(label, fn, paper=""):
        table.add_row(label, *[fn(r) for r in results.values()], paper)

    def metric(attr, fmt, scale=1.0):
        def get(r: DriveResult) -> str:
            if r.metrics is None:
                return "-"
            value = getattr(r.metrics, attr) * scale
            if not np.isfinite(value):
                return "no estimate"  # the filter never started: nothing to measure
            return format(value, fmt)

        return get

    row("frames", lambda r: str(len(r.estimates_world)))
    row("with estimate", metric("coverage", ".0%"))
    row("RMSE (m)", metric("position_rmse_m", ".3f"), f"{PAPER_RMSE_M}")
    row("median (m)", metric("position_median_m", ".3f"))
    row("heading RMSE (°)", metric("heading_rmse_deg", ".2f"))
    row("< 0.25 m & 2°", metric("within_0_25m_2deg", ".1%"))
    row("< 0.5 m & 5°", metric("within_0_5m_5deg", ".1%"))
    row("with hypotheses", lambda r: f"{np.mean(r.n_hypotheses > 0):.0%}")
    order = ["decode", "features", "vlad", "retrieval", "lookup", "matching", "pnp", "total"]
    seen = {k for r in results.values() for t in r.server_timings_ms for k in t}
    stages = [s for s in order if s in seen] + sorted(seen - set(order))
    for stage in stages:

        def pct(r, stage=stage):
            v = [t[stage] for t in r.server_timings_ms if stage in t]
            return f"{np.percentile(v, 50):.1f} / {np.percentile(v, 99):.1f}" if v else "-"

        row(f"{stage} ms p50/p99", pct)
    row("round trip ms p50", lambda r: f"{np.nanpercentile(r.latency_ms, 50):.1f}")
    row("frames / s", lambda r: f"{r.frames_per_s:.1f}", "~10 (i7)")
    return table


def _map_positions(client, map_id: int) -> tuple[np.ndarray, list[dict]]:
    items, offset = [], 0
    while True:
        page = client.request(
            "GET", f"/v1/maps/{map_id}/entries", params={"limit": 1000, "offset": offset}
        ).json()
        items += page["items"]
        offset += len(page["items"])
        if not page["items"] or offset >= page["total"]:
            break
    xy = np.array([[e["pose"]["x_m"], e["pose"]["y_m"]] for e in items]).reshape(-1, 2)
    return xy, items


def make_plots(out: Path, client, map_id: int, dataset, results: dict[str, DriveResult]):
    import cv2

    from monoloc.demo.plots import plot_errors, plot_retrieval, plot_trajectories

    map_xy, entries = _map_positions(client, map_id)
    paths = [out / "trajectories.png", out / "errors.png", out / "retrieval.png"]
    plot_trajectories(
        paths[0],
        map_xy,
        {name: (r.run.truth_world, r.estimates_world) for name, r in results.items()},
    )
    plot_errors(
        paths[1],
        {
            name: (r.run.timestamps_s, r.run.truth_world, r.estimates_world)
            for name, r in results.items()
        },
    )
    # One query frame beside its top retrieved entries (found back by their timestamp).
    query = results["query"].run
    frame = len(query) // 2
    answer = client.localize(map_id, query.image_paths[frame].read_bytes()).raw
    map_seq = dataset.root / "sequences" / dataset.sequences["map"]
    times = kitti.read_times(map_seq / "times.txt")
    by_id = {e["id"]: e for e in entries}
    shown = []
    for item in answer.get("retrieved", [])[:3]:
        entry = by_id.get(item["entry_id"])
        if entry is None or entry.get("timestamp_s") is None:
            continue
        index = int(np.argmin(np.abs(times - entry["timestamp_s"])))
        image = cv2.imread(str(map_seq / "image_0" / f"{index:06d}.png"), cv2.IMREAD_GRAYSCALE)
        if image is not None and "night" not in entry.get("tags", []):
            shown.append(
                (
                    f"entry {entry['id']} (map frame {index}), VLAD distance "
                    f"{item['distance']:.3f}",
                    image,
                )
            )
    query_image = cv2.imread(str(query.image_paths[frame]), cv2.IMREAD_GRAYSCALE)
    plot_retrieval(paths[2], query_image, shown)
    return paths

"""Human-facing output of the map commands: progress bar, summary tables, JSON.

Degrees appear here only (docs/method.md section 9: radians everywhere else).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager

import numpy as np
from rich.console import Console
from rich.table import Table


@contextmanager
def progress_bar(description: str) -> Iterator[Callable[[int, int], None]]:
    """A rich progress bar; yields ``update(done, total)``."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    with Progress(*columns, console=Console(stderr=True), transient=False) as progress:
        task = progress.add_task(description, total=None)

        def update(done: int, total: int) -> None:
            progress.update(task, completed=done, total=total)

        yield update


def print_ingest_summary(summary, console: Console | None = None) -> None:
    console = console or Console()
    table = Table("ingestion", "value", title=f"run {summary.run_id} into map {summary.map_id}")
    table.add_row("frames", f"{summary.frames_done} of {summary.frames_total}")
    table.add_row("entries added", str(summary.entries_added))
    table.add_row("frames skipped", str(summary.frames_skipped))
    for reason, n in sorted(summary.skip_reasons.items()):
        table.add_row(f"  {reason}", str(n))
    table.add_row(
        "3D keypoints per entry",
        f"mean {summary.points_mean:.0f}, min {summary.points_min}"
        if summary.entries_added
        else "-",
    )
    table.add_row("time", f"{summary.elapsed_s:.1f} s ({summary.frames_per_s:.1f} frames/s)")
    table.add_row("map version", str(summary.map_version))
    if summary.registration is not None:
        table.add_row("registered to the map", registration_text(summary.registration))
    if summary.interrupted:
        table.add_row("status", "interrupted (run again to resume)")
    console.print(table)


def registration_text(reg: dict) -> str:
    """One line for a run's registration summary (``RunCorrection.summary``)."""
    mean_x, mean_y = reg["offset_mean_m"]
    used = f"{reg['frames_used']} of {reg['frames_measured']} localized frames used"
    if not reg["offset_max_m"]:
        return f"{used}; not moved"
    return (
        f"{used}; moved by x {mean_x:+.3f} m, y {mean_y:+.3f} m on average "
        f"(at most {reg['offset_max_m']:.3f} m)"
    )


def print_stats(stats, console: Console | None = None) -> None:
    console = console or Console()
    m = stats.record
    c = m.camera
    table = Table("map", "value", title=f"map {m.name} (id {m.id})")
    table.add_row("entries", str(m.n_entries))
    table.add_row("version", str(m.version))
    table.add_row(
        "camera",
        f"{c.width_px}x{c.height_px}, fx {c.fx:.3f} fy {c.fy:.3f} cx {c.cx:.3f} cy {c.cy:.3f}",
    )
    table.add_row(
        "vocabulary",
        f"id {stats.vocabulary.id}, {stats.vocabulary.version_hash}: "
        f"{stats.vocabulary.description[:100]}",
    )
    if stats.stale_vlads:
        table.add_row(
            "stale VLADs",
            f"{stats.stale_vlads} entries on another vocabulary (re-run `monoloc map vocab`)",
        )
    table.add_row(
        "calibration",
        "calibrated" if m.calibration else "not calibrated (default measurement model)",
    )
    from monoloc.server.vision.features import rule_is_current, rule_text

    table.add_row(
        "ORB corners",
        rule_text(m.features)
        + (
            " (the default)"
            if rule_is_current(m.features)
            else " (not the default: served by its own rule; upload its runs into a new map "
            "to rebuild it with the default)"
        ),
    )
    table.add_row(
        "3D keypoints per entry",
        f"mean {stats.points_mean:.0f}, min {stats.points_min}, max {stats.points_max}"
        if m.n_entries
        else "-",
    )
    table.add_row("tags", ", ".join(f"{t}: {n}" for t, n in stats.tags.items()) or "-")
    console.print(table)
    runs = Table(
        "run",
        "kind",
        "format",
        "status",
        "frames",
        "entries",
        "skipped",
        "registered",
        "source",
        title="runs",
    )
    for r in stats.runs:
        skipped = f"{r.frames_skipped} " + (str(r.skip_reasons) if r.skip_reasons else "")
        runs.add_row(
            str(r.id),
            r.kind,
            r.source_format,
            r.status,
            f"{r.frames_done}/{r.frames_total}",
            str(r.entries_added),
            skipped,
            registration_text(r.registration) if r.registration is not None else "-",
            r.source_name[-60:],
        )
    if stats.runs:
        console.print(runs)


def localization_dict(record, result, version: int) -> dict:
    """The result of ``MapRegistry.localize`` as JSON-ready data (radians, metres)."""
    return {
        "map": record.name,
        "map_id": record.id,
        "map_version": version,
        "n_features": result.n_features,
        "retrieved": [
            {"entry_id": int(i), "e_vlad": float(d)}
            for i, d in zip(result.retrieved_ids, result.retrieved_distances, strict=True)
        ],
        "hypotheses": [
            {
                "entry_id": h.entry_id,
                "pose_world": [float(v) for v in h.pose_world],
                "entry_pose_world": [float(v) for v in h.entry_pose_world],
                "T_world_from_cam": [[float(v) for v in row] for row in h.T_world_from_cam],
                "e_vlad": h.e_vlad,
                "n_matches": h.n_matches,
                "n_inliers": h.n_inliers,
                "reprojection_error_px": h.reprojection_error_px,
            }
            for h in result.hypotheses
        ],
        "rejected": [{"entry_id": i, "reason": why} for i, why in result.rejected],
        "timings_ms": result.timings_ms,
    }


def print_localization(
    record,
    result,
    version: int,
    as_json: bool,
    console: Console | None = None,
    warm_up_s: float | None = None,
    map_load_s: float | None = None,
    warm_timings_ms: Sequence[dict[str, float]] = (),
) -> None:
    """The hypotheses table and stage timings. ``warm_up_s``: what loading the compiled
    kernels cost this process before the query; ``map_load_s``: reading the map's index
    and entries before it (neither is in the stage timings); ``warm_timings_ms``: the
    stage timings of repeats of the same query, shown as warm p50 beside the first's."""
    warm = {
        stage: float(np.median([t[stage] for t in warm_timings_ms]))
        for stage in (result.timings_ms if warm_timings_ms else ())
    }
    if as_json:
        answer = localization_dict(record, result, version)
        answer["timings_are"] = "cold: the first query of this process"
        if warm_up_s is not None:
            answer["kernel_warm_up_ms"] = round(warm_up_s * 1e3, 1)
        if map_load_s is not None:
            answer["map_load_ms"] = round(map_load_s * 1e3, 1)
        if warm:
            answer["warm_timings_ms_p50"] = warm
            answer["warm_repeats"] = len(warm_timings_ms)
        print(json.dumps(answer, indent=2))
        return
    console = console or Console()
    table = Table(
        "entry",
        "x (m)",
        "y (m)",
        "heading (deg)",
        "entry x",
        "entry y",
        "e_vlad",
        "inliers",
        "matches",
        "reproj (px)",
        title=f"{len(result.hypotheses)} hypotheses from {len(result.retrieved_ids)} "
        f"retrieved entries (map {record.name} v{version})",
    )
    best = result.best
    for h in sorted(result.hypotheses, key=lambda h: -h.n_inliers):
        x, y, yaw = h.pose_world
        mark = " *" if h is best else ""
        table.add_row(
            f"{h.entry_id}{mark}",
            f"{x:.2f}",
            f"{y:.2f}",
            f"{math.degrees(yaw):.1f}",
            f"{h.entry_pose_world[0]:.2f}",
            f"{h.entry_pose_world[1]:.2f}",
            f"{h.e_vlad:.3f}",
            str(h.n_inliers),
            str(h.n_matches),
            f"{h.reprojection_error_px:.2f}",
        )
    console.print(table)
    console.print(f"{result.n_features} features")
    timings = Table(
        "stage",
        "first query (ms, cold)",
        *([f"warm p50 of {len(warm_timings_ms)} repeats (ms)"] if warm else []),
        title="stage timings",
    )
    for stage, ms in result.timings_ms.items():
        timings.add_row(stage, f"{ms:.2f}", *([f"{warm[stage]:.2f}"] if warm else []))
    console.print(timings)
    notes = ["first query: the first in this process (caches and allocations cold)"]
    if warm_up_s is not None:
        notes.append(
            f"no compilation in it: the compiled kernels were loaded before it "
            f"({warm_up_s * 1e3:.0f} ms, once per process; `monoloc serve` does it at start)"
        )
    if map_load_s is not None:
        notes.append(f"the map's index and entries were read before it ({map_load_s * 1e3:.0f} ms)")
    if not warm:
        notes.append("--repeat N adds the warm figures of N repeats")
    console.print("; ".join(notes) + ".")
    if result.rejected:
        console.print(
            f"rejected: {len(result.rejected)} "
            f"({'; '.join(f'{i}: {r}' for i, r in result.rejected[:5])})"
        )

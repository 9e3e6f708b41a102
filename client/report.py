"""Human-facing summaries of a drive (degrees appear only here)."""

from __future__ import annotations

import numpy as np


def summary_rows(result) -> list[tuple[str, str]]:
    """(label, value) rows of a DriveResult: accuracy, dropped frames, latency, rate."""
    rows = [("frames", str(len(result.estimates_world)))]
    m = result.metrics
    if m is not None:
        rows += [
            ("position RMSE", f"{m.position_rmse_m:.3f} m"),
            ("position median", f"{m.position_median_m:.3f} m"),
            ("heading RMSE", f"{m.heading_rmse_deg:.2f} deg"),
            ("within 0.25 m / 2 deg", f"{100 * m.within_0_25m_2deg:.1f} %"),
            ("within 0.5 m / 5 deg", f"{100 * m.within_0_5m_5deg:.1f} %"),
            ("within 5 m / 10 deg", f"{100 * m.within_5m_10deg:.1f} %"),
        ]
    lat = result.latency_ms[np.isfinite(result.latency_ms)]
    rows += [
        ("frames with hypotheses", f"{100 * np.mean(result.n_hypotheses > 0):.1f} %"),
        ("dropped by the server", str(int(result.dropped.sum()))),
        ("server errors", str(len(result.errors))),
        (
            "round trip p50 / p99",
            f"{np.percentile(lat, 50):.1f} / {np.percentile(lat, 99):.1f} ms" if len(lat) else "-",
        ),
        ("frames per second", f"{result.frames_per_s:.1f}"),
    ]
    return rows


def metrics_table(result):
    from rich.table import Table

    table = Table(title=f"drive {result.run.name}")
    table.add_column("metric")
    table.add_column("value", justify="right")
    for label, value in summary_rows(result):
        table.add_row(label, value)
    return table

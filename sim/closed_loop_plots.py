"""Figures of closed-loop drives, like the paper's: trajectories against the ground
truth, localization error over time (dead-reckoning intervals shaded: frames without
hypotheses), and localization error against tracking error."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from monoloc.sim.closed_loop import LoopResult
from monoloc.sim.closed_loop_metrics import episodes
from monoloc.sim.closed_loop_record import localization_error_m

COLOURS = {"open": "tab:blue", "closed": "tab:red", "closed+offcenter": "tab:green"}


def plot_cases(
    results: dict[str, LoopResult],
    out_dir: Path,
    prefix: str = "closed_loop",
    reference_xy: np.ndarray | None = None,
    spike_threshold_m: float | None = None,
) -> list[Path]:
    """Three PNGs under ``out_dir``: ``<prefix>_trajectories.png``,
    ``<prefix>_errors.png``, ``<prefix>_loc_vs_tracking.png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []

    fig, ax = plt.subplots(figsize=(7, 6))
    if reference_xy is not None:
        ax.plot(*reference_xy.T, color="0.7", lw=1, ls="--", label="reference (centre line)")
    for name, r in results.items():
        c = COLOURS.get(name)
        truth = r.frames["truth_cam"]
        ax.plot(truth[:, 0], truth[:, 1], color=c, lw=1.2, label=f"{name}: true")
        est = r.estimates_world
        ax.plot(est[:, 0], est[:, 1], ".", color=c, ms=2, label=f"{name}: estimate")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(fontsize=7)
    ax.set_title("trajectories (camera) against the ground truth")
    paths.append(_save(fig, out_dir / f"{prefix}_trajectories.png"))

    fig, axes = plt.subplots(len(results), 1, figsize=(9, 2.3 * len(results)), sharex=True)
    axes = np.atleast_1d(axes)
    for ax, (name, r) in zip(axes, results.items(), strict=True):
        t = r.frames["t_s"]
        err = localization_error_m(r)
        ax.plot(t, 100 * err, color=COLOURS.get(name), lw=1)
        ax.plot(t, 100 * np.abs(r.frames["lateral_m"]), color="0.4", lw=0.8, ls=":")
        for a, b in episodes(r.frames["n_hypotheses"] == 0):
            ax.axvspan(t[a], t[min(b, len(t) - 1)], color="orange", alpha=0.25, lw=0)
        if spike_threshold_m is not None:
            ax.axhline(100 * spike_threshold_m, color="k", lw=0.6, ls="--")
        ax.set_ylabel("cm")
        ax.set_title(
            f"{name}: localization error (solid), |lateral tracking error| (dotted); "
            "shaded: dead reckoning (no hypotheses)",
            fontsize=8,
        )
    axes[-1].set_xlabel("time (s)")
    paths.append(_save(fig, out_dir / f"{prefix}_errors.png"))

    fig, ax = plt.subplots(figsize=(6, 5))
    for name, r in results.items():
        err = localization_error_m(r)
        ok = np.isfinite(err)
        ax.scatter(
            100 * np.abs(r.frames["lateral_m"][ok]), 100 * err[ok], s=5,
            color=COLOURS.get(name), label=name, alpha=0.6,
        )  # fmt: skip
    ax.set_xlabel("|lateral tracking error| (cm)")
    ax.set_ylabel("localization error (cm)")
    ax.legend()
    ax.set_title("localization error against tracking error")
    paths.append(_save(fig, out_dir / f"{prefix}_loc_vs_tracking.png"))
    return paths


def _save(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path

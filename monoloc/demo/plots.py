"""PNG plots a person can read: trajectories on the map, errors over time, retrieval."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _figure(*args, **kwargs):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt, *plt.subplots(*args, **kwargs)


def plot_trajectories(
    path: Path, map_xy: np.ndarray, runs: dict[str, tuple[np.ndarray, np.ndarray]]
):
    """Top-down view: map entries (grey), and per run the truth and the estimate (N, 3)."""
    plt, fig, axes = _figure(1, len(runs), figsize=(6 * len(runs), 6), squeeze=False)
    for ax, (name, (truth, est)) in zip(axes[0], runs.items(), strict=True):
        ax.scatter(map_xy[:, 0], map_xy[:, 1], s=4, c="0.75", label="map entries")
        ax.plot(truth[:, 0], truth[:, 1], "k-", lw=1.5, label="ground truth")
        ax.plot(est[:, 0], est[:, 1], "r.", ms=3, label="monoloc estimate")
        ax.set_title(name)
        ax.set_xlabel("X (m)")
        ax.set_ylabel("Y (m)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_errors(path: Path, runs: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]):
    """Position error (m) and heading error (deg) over time per run: (t, truth, est)."""
    plt, fig, (ax_p, ax_h) = _figure(2, 1, figsize=(10, 6), sharex=True)
    for name, (t, truth, est) in runs.items():
        err = np.linalg.norm(est[:, :2] - truth[:, :2], axis=1)
        yaw = np.degrees(np.abs(np.angle(np.exp(1j * (est[:, 2] - truth[:, 2])))))
        ax_p.plot(t - t[0], err, label=name)
        ax_h.plot(t - t[0], yaw, label=name)
    ax_p.axhline(0.25, color="0.5", ls="--", lw=0.8)
    ax_p.set_ylabel("position error (m)")
    ax_p.set_yscale("symlog", linthresh=0.1)
    ax_h.set_ylabel("heading error (deg)")
    ax_h.set_yscale("symlog", linthresh=1.0)
    ax_h.set_xlabel("time (s)")
    ax_p.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_retrieval(path: Path, query: np.ndarray, retrieved: list[tuple[str, np.ndarray]]):
    """A query frame above its top retrieved map images (grayscale arrays)."""
    n = 1 + len(retrieved)
    plt, fig, axes = _figure(n, 1, figsize=(7, 1.25 * n))
    axes = np.atleast_1d(axes)
    axes[0].imshow(query, cmap="gray", vmin=0, vmax=255)
    axes[0].set_title("query frame", fontsize=9)
    for ax, (label, image) in zip(axes[1:], retrieved, strict=True):
        ax.imshow(image, cmap="gray", vmin=0, vmax=255)
        ax.set_title(label, fontsize=9)
    for ax in axes:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)

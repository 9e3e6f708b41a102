"""A one-page look at an indoor (TUM RGB-D) dataset: each room from above (walls,
track tape, the runs' ground-truth paths) and a contact sheet of rgb and depth frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from monoloc.core.errors import NotFoundError
from monoloc.core.formats import tum
from monoloc.sim import tum_writer as tw
from monoloc.sim.indoor.track import TrackShape, centre_line


def write_indoor_preview(dataset: Path, info: dict, out: Path, per_run: int = 4) -> Path:
    """Write ``out`` (PNG) for the indoor dataset at ``dataset`` described by ``info``
    (its dataset.json); returns ``out``."""
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dataset = Path(dataset)
    sequences = info["sequences"]
    n = len(sequences)
    fig = plt.figure(figsize=(4 + 3.2 * (per_run + 1), max(4.0, 1.6 * n + 1)), dpi=100)
    grid = fig.add_gridspec(n, per_run + 3)
    rooms = sorted({seq["room"] for seq in sequences})
    rows = np.array_split(np.arange(n), len(rooms))
    axes = {
        r: fig.add_subplot(grid[a[0] : a[-1] + 1, :2]) for r, a in zip(rooms, rows, strict=True)
    }
    for name, ax in axes.items():
        room = info["rooms"][name]
        (w, d), (cx, cy) = room["size_m"], room["centre_xy"]
        ax.add_patch(plt.Rectangle((cx - w / 2, cy - d / 2), w, d, fill=False, lw=1.5))
        shape = room["track_shape"]
        track = TrackShape(
            tuple(shape["centre_xy"]),
            tuple(shape["semi_axes"]),
            shape["exponent"],
            tuple(tuple(h) for h in shape["harmonics"]),
            shape["start_theta_rad"],
        )
        xy = centre_line(track)
        tangent = np.gradient(xy, axis=0)
        left = (
            np.stack([-tangent[:, 1], tangent[:, 0]], 1) / np.linalg.norm(tangent, axis=1)[:, None]
        )
        for side in (-0.5, 0.5):
            edge = xy + left * side * room["track_width_m"]
            ax.plot(edge[:, 0], edge[:, 1], color="0.6", lw=0.8)
        ax.set_aspect("equal")
        ax.set_title(
            f"{name} room ({room['floor']} floor): tape and paths, z-up world (m)", fontsize=8
        )
    for k, seq in enumerate(sequences):
        run_dir = dataset / seq.get("path", seq["id"])
        if not (run_dir / "rgb.txt").exists():
            raise NotFoundError(f"{run_dir / 'rgb.txt'} does not exist")
        T = tum.read_trajectory(run_dir / "groundtruth.txt").T_world_from_cam
        ax_map = axes[seq["room"]]
        ax_map.plot(T[:, 0, 3], T[:, 1, 3], lw=1.0, label=f"{seq['id']} ({seq['frames']} frames)")
        ax_map.plot(T[0, 0, 3], T[0, 1, 3], "o", ms=3, color="k")
        _, rgb = tum.read_file_list(run_dir / "rgb.txt")
        _, depth = tum.read_file_list(run_dir / "depth.txt")
        picks = np.linspace(0, len(rgb) - 1, per_run).astype(int)
        for j, idx in enumerate(picks):
            ax = fig.add_subplot(grid[k, 2 + j])
            ax.imshow(
                cv2.imread(str(run_dir / rgb[idx]), cv2.IMREAD_GRAYSCALE),
                cmap="gray",
                vmin=0,
                vmax=255,
            )
            ax.set_axis_off()
            ax.set_title(f"{seq['id']} #{idx}", fontsize=7)
        ax = fig.add_subplot(grid[k, 2 + per_run])
        shown = ax.imshow(tw.read_depth(run_dir / depth[picks[0]]), cmap="turbo", vmin=0, vmax=8)
        ax.set_axis_off()
        ax.set_title(f"{seq['id']} depth #{picks[0]} (0-8 m)", fontsize=7)
        if k == 0:
            fig.colorbar(shown, ax=ax, fraction=0.04)
    for ax in axes.values():
        ax.legend(fontsize=6, loc="best")
    fig.tight_layout()
    out = Path(out)
    fig.savefig(out)
    plt.close(fig)
    return out

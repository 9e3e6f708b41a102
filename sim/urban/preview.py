"""A one-page look at an urban (KITTI layout) dataset: the routes of each district from
above and a contact sheet of frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from monoloc.core.formats.kitti import read_poses
from monoloc.core.geometry import kitti_to_zup


def write_urban_preview(dataset: Path, info: dict, out: Path, per_run: int = 4) -> Path:
    """Write ``out`` (PNG) for the urban dataset at ``dataset`` described by ``info``
    (its dataset.json); returns ``out``."""
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dataset = Path(dataset)
    sequences = info["sequences"]
    n = len(sequences)
    fig = plt.figure(figsize=(4 + 3.2 * per_run, max(4.0, 1.1 * n + 1)), dpi=110)
    grid = fig.add_gridspec(n, per_run + 2)
    districts = sorted({seq.get("district", "main") for seq in sequences})
    rows = np.array_split(np.arange(n), len(districts))
    axes = {
        d: fig.add_subplot(grid[r[0] : r[-1] + 1, :2]) for d, r in zip(districts, rows, strict=True)
    }
    for k, seq in enumerate(sequences):
        poses = read_poses(dataset / "poses" / f"{seq['id']}.txt")
        xy = kitti_to_zup(poses)[:, :2, 3]
        ax_map = axes[seq.get("district", "main")]
        ax_map.plot(
            xy[:, 0],
            xy[:, 1],
            lw=1.2,
            label=f"{seq['id']} {seq['run']} ({seq['lighting']['name']})",
        )
        ax_map.plot(xy[0, 0], xy[0, 1], "o", ms=3, color="k")
        images = sorted((dataset / "sequences" / seq["id"] / "image_0").glob("*.png"))
        picks = np.linspace(0, len(images) - 1, per_run).astype(int) if images else []
        for j, idx in enumerate(picks):
            ax = fig.add_subplot(grid[k, 2 + j])
            ax.imshow(
                cv2.imread(str(images[idx]), cv2.IMREAD_GRAYSCALE), cmap="gray", vmin=0, vmax=255
            )
            ax.set_axis_off()
            ax.set_title(f"{seq['id']} {seq['run']} #{idx}", fontsize=7)
    for district, ax_map in axes.items():
        ax_map.set_aspect("equal", adjustable="datalim")
        ax_map.set_title(f"{district} district: routes (z-up world, m)", fontsize=9)
        ax_map.legend(fontsize=7, loc="best")
    fig.tight_layout()
    out = Path(out)
    fig.savefig(out)
    plt.close(fig)
    return out

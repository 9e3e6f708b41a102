"""Fixtures of the shard suites: a sim street whose map run is split at a tile border
(entries west of it for group 'west', east of it for group 'east'), and the query run
that drives across it. The replica processes and nginx come from tests/fleet's helpers."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "fleet"))

from shard_helpers import SplitStreet  # noqa: E402


@pytest.fixture(scope="session")
def split_street(tmp_path_factory) -> SplitStreet:
    """A 28 m street along x, map run (00) and query run (01), 40 frames, LiDAR; the tile
    border at x = 14 m."""
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.lidar import LidarConfig

    root = tmp_path_factory.mktemp("split_street")
    config = GenerateConfig(
        size="small",
        runs=("map", "query"),
        max_frames=40,
        write_depth=False,
        lidar=LidarConfig(azimuth_steps=1000),
        seed=1,
    )
    generate_dataset(config, root)
    return SplitStreet(root, border_x_m=14.0)

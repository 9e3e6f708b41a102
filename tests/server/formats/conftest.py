"""Fixtures of the format tests: a tiny exact sim city (a map run and a query run of 8
half-size frames, no recording errors) and a migrated SQLite database per test."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def sim_city(tmp_path_factory) -> Path:
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.lidar import LidarConfig
    from monoloc.sim.recording import RecordingErrors

    root = tmp_path_factory.mktemp("formats_city")
    config = GenerateConfig(
        seed=3,
        runs=("map", "query"),
        max_frames=8,
        image_scale=0.5,
        write_depth=True,
        errors=RecordingErrors.none(),
        lidar=LidarConfig(azimuth_steps=1000),
    )
    generate_dataset(config, root)
    return root


@pytest.fixture(scope="session")
def map_run(sim_city):
    from monoloc.server.ingest.sources import read_kitti_sequence

    return read_kitti_sequence(sim_city, "00")


@pytest.fixture(scope="session")
def query_run(sim_city):
    from monoloc.server.ingest.sources import read_kitti_sequence

    return read_kitti_sequence(sim_city, "01")

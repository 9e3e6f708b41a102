"""Fixtures of the format tests: a tiny exact sim city (a map run and a query run of 8
half-size frames, no recording errors) and a migrated SQLite database per test."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from monoloc.server.settings import Settings
from monoloc.server.storage.db import create_engine_for, make_session_factory


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
    from monoloc.server.ingest.kitti import read_kitti_sequence

    return read_kitti_sequence(sim_city, "00")


@pytest.fixture(scope="session")
def query_run(sim_city):
    from monoloc.server.ingest.kitti import read_kitti_sequence

    return read_kitti_sequence(sim_city, "01")


@pytest.fixture
def settings(tmp_path: Path, database_url) -> Settings:
    extra = {"database_url": database_url} if database_url else {}
    return Settings(data_dir=tmp_path / "data", **extra)


@pytest.fixture
def factory(settings: Settings) -> Iterator:
    from monoloc.server.storage.migrate import upgrade_database

    upgrade_database(settings.database_url)
    engine = create_engine_for(settings)
    yield make_session_factory(engine)
    engine.dispose()

"""Session fixtures of the end-to-end tests: a tiny sim city (map + query run, full
KITTI resolution, generated once per session) and a live server on a real SQLite file
holding the map run, uploaded and ingested through the HTTP API."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from e2e_helpers import (
    ADMIN_KEY,
    MAP_SEQ,
    SIM_FRAMES,
    LiveMap,
    create_keys,
    live_server,
    make_settings,
    upload_map_run,
)


@pytest.fixture(scope="session")
def sim_city(tmp_path_factory) -> Path:
    """Map run 00 and query run 01 (lateral offsets, moved cars, other light) of one
    street, SIM_FRAMES frames each at 1241 x 376, with vehicle.txt and dataset.json."""
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.lidar import LidarConfig

    root = tmp_path_factory.mktemp("sim_city")
    config = GenerateConfig(
        runs=("map", "query"),
        max_frames=SIM_FRAMES,
        lidar=LidarConfig(azimuth_steps=1000),
        seed=0,
    )
    generate_dataset(config, root)
    return root


@pytest.fixture(scope="session")
def live_map(sim_city, tmp_path_factory) -> Iterator[LiveMap]:
    """A real server (uvicorn, one worker thread) with map 'city' = the sim's map run."""
    from monoloc.client.api import MonolocClient

    data_dir = tmp_path_factory.mktemp("server") / "data"
    with live_server(make_settings(data_dir)) as (url, app):
        with MonolocClient(url, ADMIN_KEY, timeout_s=60.0) as admin:
            keys = create_keys(admin)
            map_id = upload_map_run(admin, "city", sim_city, MAP_SEQ)
        yield LiveMap(url, app, map_id, "city", keys, data_dir, sim_city)

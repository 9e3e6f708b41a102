"""Fixtures of the API tests: a tiny sim dataset (once per session), apps on real SQLite
files in tmp_path, API keys of each scope, and a map ingested once per session through
the API itself (tests get their own copy of its data directory)."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from api_helpers import (
    MAP_FRAMES,
    SIM_SCALE,
    Keys,
    TestClient,
    camera_of,
    create_keys,
    make_settings,
    open_client,
    tar_sequence,
    wait_job,
)


@pytest.fixture(scope="session")
def sim_dataset(tmp_path_factory) -> Path:
    """A map run and a query run of the same street, 16 frames each, KITTI size."""
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.lidar import LidarConfig

    root = tmp_path_factory.mktemp("sim")
    config = GenerateConfig(
        size="small",
        runs=("map", "query"),
        max_frames=MAP_FRAMES,
        image_scale=SIM_SCALE,
        write_depth=True,
        lidar=LidarConfig(azimuth_steps=1000),
        seed=0,
    )
    generate_dataset(config, root)
    return root


@dataclass(frozen=True)
class IngestedMap:
    data_dir: Path
    map_id: int
    keys: Keys
    job: dict


def _create_street_map(client, keys: Keys, dataset: Path) -> int:
    """Create the empty map 'street' with the dataset's camera; its id."""
    r = client.post(
        "/v1/maps",
        json={"name": "street", "camera": camera_of(dataset)},
        headers=keys.header("admin"),
    )
    assert r.status_code == 201, r.text
    return r.json()["id"]


@pytest.fixture(scope="session")
def ingested(sim_dataset, tmp_path_factory) -> IngestedMap:
    """Map 'street' with the map run ingested through the API (upload + job)."""
    data_dir = tmp_path_factory.mktemp("ingested") / "data"
    with open_client(make_settings(data_dir)) as client:
        keys = create_keys(client)
        map_id = _create_street_map(client, keys, sim_dataset)
        r = client.post(
            f"/v1/maps/{map_id}/runs",
            files={"archive": ("map.tar.gz", tar_sequence(sim_dataset), "application/gzip")},
            data={"format": "kitti", "kind": "map"},
            headers=keys.header("write"),
        )
        assert r.status_code == 202, r.text
        job = wait_job(client, r.json()["job"]["id"], keys.header("write"))
        assert job["state"] == "done", job
    return IngestedMap(data_dir, map_id, keys, job)


@pytest.fixture
def map_copy(ingested, tmp_path) -> IngestedMap:
    """A private copy of the ingested map's data directory."""
    data_dir = tmp_path / "data"
    shutil.copytree(ingested.data_dir, data_dir)
    return IngestedMap(data_dir, ingested.map_id, ingested.keys, ingested.job)


@pytest.fixture
def client_on_copy(map_copy) -> Iterator[TestClient]:
    with open_client(make_settings(map_copy.data_dir)) as client:
        yield client


@pytest.fixture
def fresh(tmp_path) -> Iterator[tuple[TestClient, Keys]]:
    """An app on an empty data directory, with keys of each scope."""
    with open_client(make_settings(tmp_path / "data")) as client:
        yield client, create_keys(client)


@pytest.fixture
def empty_map_app(sim_dataset, tmp_path):
    """(client, keys, map id, data dir) of an app with one empty map."""
    data_dir = tmp_path / "data"
    with open_client(make_settings(data_dir)) as client:
        keys = create_keys(client)
        yield client, keys, _create_street_map(client, keys, sim_dataset), data_dir

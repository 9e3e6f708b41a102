"""Fixtures of the fleet suites: `monoloc serve` replica processes on a real PostgreSQL
(the throwaway server of tests/conftest.py), a small sim street to map with."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from fleet_helpers import (
    ADMIN_KEY,
    FRAMES,
    Fleet,
    Replica,
    create_map,
    free_port,
    replica_env,
    upload_run,
    wait_job,
)


@pytest.fixture(scope="session")
def street(tmp_path_factory) -> Path:
    """A map run and a query run of one street, KITTI layout, LiDAR."""
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.lidar import LidarConfig

    root = tmp_path_factory.mktemp("street")
    config = GenerateConfig(
        size="small",
        runs=("map", "query"),
        max_frames=FRAMES,
        write_depth=False,
        lidar=LidarConfig(azimuth_steps=1000),
        seed=1,
    )
    generate_dataset(config, root)
    return root


@pytest.fixture(scope="module")
def fleet(postgres_admin_url, street, tmp_path_factory) -> Iterator[Fleet]:
    """Two replicas (own data directories, a shared uploads directory) on one fresh
    PostgreSQL database, with keys and map 'street' ingested through replica a."""
    from pg_cluster import fresh_database

    from monoloc.server.storage.migrate import upgrade_database

    root = tmp_path_factory.mktemp("fleet")
    with fresh_database(postgres_admin_url) as url:
        upgrade_database(url)  # once, as docker/compose.yaml's migrate service does
        env = replica_env(url, root / "shared-uploads")
        made = [Replica(n, free_port(), root / n / "data", env) for n in ("a", "b")]
        try:
            for replica in made:
                replica.start()
            for replica in made:
                replica.wait_ready()
            a = made[0].url
            keys = {"admin": ADMIN_KEY}
            for name, scope in (("localize", "localize"), ("write", "map:write")):
                r = httpx.post(
                    f"{a}/v1/keys",
                    json={"name": name, "scopes": [scope]},
                    headers={"X-API-Key": ADMIN_KEY},
                    timeout=30,
                )
                assert r.status_code == 201, r.text
                keys[name] = r.json()["key"]
            map_id = create_map(a, keys, "street", street)
            job = wait_job(a, upload_run(a, keys, map_id, street, "00"), {"X-API-Key": ADMIN_KEY})
            assert job["state"] == "done", job
            yield Fleet(url, made, keys, map_id)
        finally:
            for replica in made:
                replica.stop()

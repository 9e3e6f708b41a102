"""Fixtures shared by every suite.

``database_url``: None (each suite's settings then use a SQLite file in tmp_path), or, with
``MONOLOC_TEST_POSTGRES_URL`` set to a PostgreSQL server URL whose user may create
databases (e.g. ``postgresql+psycopg://postgres@/postgres?host=/tmp&port=55432``), the URL
of a fresh database created for the test and dropped after it. ``make test-postgres``
runs the storage and ingestion suites that way.

``postgres_url``: always PostgreSQL (the replica, change-log and job-lease suites): a
fresh database on ``MONOLOC_TEST_POSTGRES_URL``'s server if set, else on a throwaway
server this session starts itself (``tests/pg_cluster.py``; ``make test`` installs the
Debian ``postgresql`` package when none is installed). Skipped only when no server can
be found at all.

``stereo_dataset``: a tiny sim city run (6 frames, half-size images, exact geometry) with
the right camera (image_1, P1), LiDAR scans and true depth images, written once per
session; tests that change it work on a copy.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Iterator
from pathlib import Path

import pytest
from pg_cluster import fresh_database, start_throwaway_postgres

POSTGRES_ADMIN_URL = os.environ.get("MONOLOC_TEST_POSTGRES_URL", "")


@pytest.fixture
def database_url() -> Iterator[str | None]:
    """None (the settings' SQLite file) or a fresh PostgreSQL database's URL."""
    if not POSTGRES_ADMIN_URL:
        yield None
        return
    with fresh_database(POSTGRES_ADMIN_URL) as url:
        yield url


@pytest.fixture(scope="session")
def postgres_admin_url() -> Iterator[str]:
    """The URL of a PostgreSQL server the tests may create databases on."""
    if POSTGRES_ADMIN_URL:
        yield POSTGRES_ADMIN_URL
        return
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    server = start_throwaway_postgres(port)
    if server is None:
        # `make test` installs Debian's postgresql: a missing server is a broken setup,
        # never a reason to pass without the tests that need it.
        pytest.fail("no PostgreSQL server installed (make test installs Debian's postgresql)")
    try:
        yield server.url
    finally:
        server.stop()


@pytest.fixture
def postgres_url(postgres_admin_url) -> Iterator[str]:
    """A fresh, empty PostgreSQL database for one test."""
    with fresh_database(postgres_admin_url) as url:
        yield url


@pytest.fixture(scope="session")
def stereo_dataset(tmp_path_factory) -> Path:
    """Dataset root of sequence 00 (a map run) with image_0, image_1, velodyne and depth."""
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.lidar import LidarConfig
    from monoloc.sim.recording import RecordingErrors

    root = tmp_path_factory.mktemp("stereo")
    config = GenerateConfig(
        seed=3,
        runs=("map",),
        max_frames=6,
        image_scale=0.5,
        write_depth=True,
        write_stereo=True,
        errors=RecordingErrors.none(),
        lidar=LidarConfig(azimuth_steps=1000),
    )
    generate_dataset(config, root)
    return root

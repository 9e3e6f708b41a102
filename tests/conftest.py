"""Fixtures shared by every suite.

``database_url``: None (each suite's settings then use a SQLite file in tmp_path), or, with
``MONOLOC_TEST_POSTGRES_URL`` set to a PostgreSQL server URL whose user may create
databases (e.g. ``postgresql+psycopg://postgres@/postgres?host=/tmp&port=55432``), the URL
of a fresh database created for the test and dropped after it. ``make test-postgres``
runs the storage and ingestion suites that way.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterator

import pytest
from sqlalchemy import create_engine, text
from sqlalchemy.engine import make_url

POSTGRES_ADMIN_URL = os.environ.get("MONOLOC_TEST_POSTGRES_URL", "")


@pytest.fixture
def database_url() -> Iterator[str | None]:
    """None (the settings' SQLite file) or a fresh PostgreSQL database's URL."""
    if not POSTGRES_ADMIN_URL:
        yield None
        return
    name = f"monoloc_test_{uuid.uuid4().hex[:12]}"
    admin = create_engine(POSTGRES_ADMIN_URL, isolation_level="AUTOCOMMIT")
    with admin.connect() as connection:
        connection.execute(text(f'CREATE DATABASE "{name}"'))
    yield make_url(POSTGRES_ADMIN_URL).set(database=name).render_as_string(hide_password=False)
    with admin.connect() as connection:
        connection.execute(text(f'DROP DATABASE "{name}" WITH (FORCE)'))
    admin.dispose()

"""Fixtures shared by the server suites: settings on a fresh data folder (SQLite in
tmp_path, or a fresh PostgreSQL database when the session has one, see tests/conftest.py)
with deadlines generous enough for a loaded machine (tests/busy_machine.py), and a
session factory on its migrated database."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from busy_machine import GENEROUS_DEADLINES

from monoloc.server.settings import Settings
from monoloc.server.storage.db import create_engine_for, make_session_factory


@pytest.fixture
def settings(tmp_path: Path, database_url) -> Settings:
    extra = {"database_url": database_url} if database_url else {}
    return Settings(data_dir=tmp_path / "data", **GENEROUS_DEADLINES, **extra)


@pytest.fixture
def factory(settings: Settings) -> Iterator:
    from monoloc.server.storage.migrate import upgrade_database

    upgrade_database(settings.database_url)
    engine = create_engine_for(settings)
    yield make_session_factory(engine)
    engine.dispose()

"""Fixtures of the storage tests: a migrated database and entry builders.

The database is a SQLite file in tmp_path, or a fresh PostgreSQL database per test with
``MONOLOC_TEST_POSTGRES_URL`` set (see tests/conftest.py).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np
import pytest
from fake_entries import fake_entry
from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from monoloc.core.camera import KITTI_CAM0
from monoloc.server.settings import Settings
from monoloc.server.storage.db import create_engine_for, make_session_factory, session_scope
from monoloc.server.storage.maps import create_map, get_or_create_vocabulary
from monoloc.server.storage.migrate import upgrade_database
from monoloc.server.storage.records import NewEntry


@pytest.fixture
def engine(settings: Settings) -> Iterator[Engine]:
    upgrade_database(settings.database_url)
    engine = create_engine_for(settings)
    yield engine
    engine.dispose()


@pytest.fixture
def factory(engine: Engine) -> sessionmaker[Session]:
    return make_session_factory(engine)


@pytest.fixture
def map_id(factory) -> int:
    """A map named 'm' with a random vocabulary, committed."""
    centres = np.random.default_rng(1).uniform(0, 255, (64, 32)).astype(np.float32)
    with session_scope(factory) as session:
        vocab, _ = get_or_create_vocabulary(session, centres, "test vocabulary")
        return create_map(session, "m", KITTI_CAM0, vocab.id).id


@pytest.fixture
def make_entry() -> Callable[..., NewEntry]:
    """Builder of valid entries: make_entry(name, x_m=0, y_m=0, yaw_rad=0, n=20, tags=())."""

    def build(
        name: str,
        x_m: float = 0.0,
        y_m: float = 0.0,
        yaw_rad: float = 0.0,
        n: int = 20,
        tags: tuple[str, ...] = (),
    ) -> NewEntry:
        return fake_entry(name, x_m, y_m, yaw_rad, n, tags)

    return build

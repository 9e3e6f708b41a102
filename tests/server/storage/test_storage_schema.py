import sqlite3
from pathlib import Path

import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import create_engine, inspect

from monoloc.server.settings import Settings, get_settings
from monoloc.server.storage.db import create_engine_for
from monoloc.server.storage.migrate import (
    current_revision,
    head_revision,
    migrations_dir,
    upgrade_database,
)
from monoloc.server.storage.models import Base

REPO = Path(__file__).resolve().parents[3]
TABLES = {"vocabularies", "maps", "runs", "entries", "entry_tags", "jobs", "api_keys"}
TABLES |= {"map_changes", "entry_images", "cameras"}


def test_upgrade_creates_exactly_the_models_schema(tmp_path):
    url = f"sqlite:///{tmp_path / 'sub' / 'x.db'}"
    assert current_revision(url) is None
    upgrade_database(url)
    upgrade_database(url)  # idempotent
    assert current_revision(url) == head_revision() == "0010"
    engine = create_engine(url)
    with engine.connect() as conn:
        assert set(inspect(conn).get_table_names()) == TABLES | {"alembic_version"}
        context = MigrationContext.configure(
            conn, opts={"compare_type": True, "compare_server_default": True}
        )
        assert compare_metadata(context, Base.metadata) == []
        fks = {
            (fk["referred_table"], fk["options"].get("ondelete"))
            for fk in inspect(conn).get_foreign_keys("entries")
        }
        assert fks == {("maps", "CASCADE"), ("runs", "SET NULL"), ("vocabularies", None)}
    engine.dispose()


def test_pragmas_set_on_every_connection(tmp_path):
    settings = Settings(data_dir=tmp_path, sqlite_synchronous="FULL", busy_timeout_ms=1234)
    upgrade_database(settings.database_url)
    engine = create_engine_for(settings)
    conns = [engine.connect() for _ in range(2)]  # two pooled connections
    try:
        for conn in conns:
            pragma = conn.exec_driver_sql
            assert pragma("PRAGMA journal_mode").scalar() == "wal"
            assert pragma("PRAGMA foreign_keys").scalar() == 1
            assert pragma("PRAGMA busy_timeout").scalar() == 1234
            assert pragma("PRAGMA synchronous").scalar() == 2  # FULL
    finally:
        for conn in conns:
            conn.close()
        engine.dispose()
    # WAL is persistent: a plain sqlite3 connection sees it too.
    raw = sqlite3.connect(tmp_path / "monoloc.db")
    assert raw.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    raw.close()


def test_settings_from_environment_not_cached(tmp_path, monkeypatch):
    monkeypatch.setenv("MONOLOC_DATA_DIR", str(tmp_path / "a"))
    first = get_settings()
    assert first.database_url == f"sqlite:///{(tmp_path / 'a' / 'monoloc.db').resolve()}"
    assert first.sqlite_synchronous == "NORMAL"
    monkeypatch.setenv("MONOLOC_DATABASE_URL", "sqlite:////elsewhere/x.db")
    monkeypatch.setenv("MONOLOC_MAX_BODY_BYTES", "1000")
    second = get_settings()
    assert second.database_url == "sqlite:////elsewhere/x.db"
    assert second.max_body_bytes == 1000
    monkeypatch.setenv("MONOLOC_SQLITE_SYNCHRONOUS", "OFF")
    with pytest.raises(ValueError):
        get_settings()


def test_migrations_are_found_in_the_source_tree():
    # The wheel ships them as monoloc.migrations (tests/test_packaging.py).
    assert migrations_dir() == REPO / "migrations"


def test_maps_record_how_their_entries_picked_their_corners(settings, factory, map_id):
    """A new map records the server's ORB rule (the grid); a map from before revision 0007
    is stamped with ORB's own rule by the upgrade, the only rule there was."""
    from alembic import command

    from monoloc.server.storage.db import session_scope
    from monoloc.server.storage.maps import get_map
    from monoloc.server.storage.migrate import alembic_config
    from monoloc.server.vision.features import OrbConfig, selection_rule

    with session_scope(factory) as session:
        recorded = get_map(session, map_id).features
    assert (
        recorded
        == selection_rule()
        == {
            "rule": "grid",
            "grid_cells": [8, 5],
            "candidates_factor": 2.0,
            "fast_thresholds": [20, 12],
            "flat_fast_corners": 150,
        }
    )
    assert selection_rule(OrbConfig(grid_cells=None)) == {"rule": "strongest"}
    factory.kw["bind"].dispose()
    command.downgrade(alembic_config(settings.database_url), "0006")
    upgrade_database(settings.database_url)
    with session_scope(factory) as session:
        record = get_map(session, map_id)
    assert record.features == {"rule": "strongest"} and record.name == "m"


def test_keys_from_before_revision_0008_see_every_map(tmp_path):
    """0008 adds api_keys.maps; keys that existed before it see every map (NULL), and a
    downgrade drops the column with the keys intact."""
    from alembic import command

    from monoloc.server.storage.db import make_session_factory, session_scope
    from monoloc.server.storage.keys import create_api_key, list_api_keys
    from monoloc.server.storage.migrate import alembic_config

    url = f"sqlite:///{tmp_path / 'k.db'}"
    command.upgrade(alembic_config(url), "0007")
    engine = create_engine(url)
    with engine.begin() as conn:
        conn.exec_driver_sql(
            "INSERT INTO api_keys (name, prefix, key_hash, scopes, created_at) "
            "VALUES ('old', 'mlk_oldoldol', 'ab', 'localize', '2026-01-01 00:00:00')"
        )
    upgrade_database(url)
    with session_scope(make_session_factory(engine)) as session:
        (old,) = list_api_keys(session)
        assert old.maps is None and old.can_see_map(12345)
        create_api_key(session, "new", ["localize"])
    command.downgrade(alembic_config(url), "0007")
    with engine.connect() as conn:
        columns = {c["name"] for c in inspect(conn).get_columns("api_keys")}
        names = [r[0] for r in conn.exec_driver_sql("SELECT name FROM api_keys ORDER BY id")]
    assert "maps" not in columns and names == ["old", "new"]
    engine.dispose()

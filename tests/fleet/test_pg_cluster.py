"""The throwaway PostgreSQL the fleet suites run on, and the schema on it."""

from __future__ import annotations

from sqlalchemy import create_engine, inspect, text

from monoloc.server.storage.migrate import upgrade_database


def test_the_suite_has_a_real_postgresql_with_the_schema(postgres_url):
    upgrade_database(postgres_url)
    engine = create_engine(postgres_url)
    try:
        with engine.connect() as connection:
            version = connection.execute(text("SHOW server_version_num")).scalar_one()
        assert int(version) >= 120000
        assert {"maps", "entries", "jobs"} <= set(inspect(engine).get_table_names())
    finally:
        engine.dispose()

"""Alembic environment of the monoloc map database.

The database URL comes, in order, from ``config.attributes["database_url"]`` or the
``sqlalchemy.url`` option (both set programmatically by ``monoloc.server.storage.migrate``),
else from the ``MONOLOC_*`` settings. On SQLite the migrations run in batch mode
(``render_as_batch``: ALTER through table copies) with foreign keys switched off for the
copy, and ``PRAGMA foreign_key_check`` must come back clean afterwards.
"""

from __future__ import annotations

from logging.config import fileConfig

from alembic import context
from sqlalchemy import pool
from sqlalchemy.engine import Connection

from monoloc.server.storage.db import create_engine_for_url
from monoloc.server.storage.models import Base

target_metadata = Base.metadata


def _database_url_and_pragmas() -> tuple[str, str, int]:
    """(url, sqlite_synchronous, busy_timeout_ms) for this migration run."""
    config = context.config
    url = config.attributes.get("database_url") or config.get_main_option("sqlalchemy.url")
    if url:
        return url, "NORMAL", 5000
    from monoloc.server.settings import get_settings

    settings = get_settings()
    return settings.database_url, settings.sqlite_synchronous, settings.busy_timeout_ms


def _run_on(connection: Connection) -> None:
    is_sqlite = connection.dialect.name == "sqlite"
    if is_sqlite:
        # Batch migrations copy tables; FK enforcement would cascade-delete children
        # when a parent table is dropped. Must be set outside a transaction.
        connection.exec_driver_sql("PRAGMA foreign_keys = OFF")
        connection.commit()
    context.configure(
        connection=connection,
        target_metadata=target_metadata,
        render_as_batch=is_sqlite,
        compare_type=True,
    )
    with context.begin_transaction():
        context.run_migrations()
    if is_sqlite:
        problems = connection.exec_driver_sql("PRAGMA foreign_key_check").fetchall()
        connection.commit()
        connection.exec_driver_sql("PRAGMA foreign_keys = ON")
        connection.commit()
        if problems:
            raise RuntimeError(f"foreign key violations after migration: {problems[:10]}")


def run_migrations_offline() -> None:
    """Emit the SQL to stdout instead of running it (``alembic upgrade head --sql``)."""
    url, _, _ = _database_url_and_pragmas()
    context.configure(
        url=url,
        target_metadata=target_metadata,
        literal_binds=True,
        render_as_batch=url.startswith("sqlite"),
        dialect_opts={"paramstyle": "named"},
    )
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_online() -> None:
    """Run the migrations on a given connection or on a fresh engine for the URL."""
    connection = context.config.attributes.get("connection")
    if connection is not None:
        _run_on(connection)
        return
    url, synchronous, busy_timeout_ms = _database_url_and_pragmas()
    engine = create_engine_for_url(
        url,
        sqlite_synchronous=synchronous,
        busy_timeout_ms=busy_timeout_ms,
        poolclass=pool.NullPool,
    )
    try:
        with engine.connect() as conn:
            _run_on(conn)
    finally:
        engine.dispose()


def main() -> None:
    config = context.config
    if config.config_file_name is not None and not config.attributes.get("skip_logging"):
        fileConfig(config.config_file_name, disable_existing_loggers=False)
    if context.is_offline_mode():
        run_migrations_offline()
    else:
        run_migrations_online()


main()

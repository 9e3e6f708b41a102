"""Run the Alembic migrations programmatically (``monoloc db upgrade``, server start-up).

The Alembic environment lives in the top-level ``migrations`` folder. It is found next
to the ``server`` package: in a source checkout / editable install that is
``<repo>/migrations``; in a wheel install ``migrations`` is shipped as a package of its
own (pyproject: ``packages.find`` includes ``migrations*``, package-data ships
``script.py.mako``), so it sits beside ``server`` in site-packages. As a last resort the
importable ``migrations`` package is used.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

from monoloc.core.errors import MonolocError
from monoloc.server.storage.db import redact_url


class MigrationError(MonolocError):
    """The schema could not be brought up to date (missing scripts, failed revision)."""


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else repr(exc)


def migrations_dir() -> Path:
    """The folder holding ``env.py`` and ``versions/``; raises MigrationError if absent."""
    candidates = [Path(__file__).resolve().parents[2] / "migrations"]
    spec = importlib.util.find_spec("monoloc.migrations")
    if spec is not None and spec.submodule_search_locations:
        candidates.extend(Path(p) for p in spec.submodule_search_locations)
    for candidate in candidates:
        if (candidate / "env.py").is_file() and (candidate / "versions").is_dir():
            return candidate
    raise MigrationError(
        "Alembic migrations not found (looked in "
        + ", ".join(str(c) for c in candidates)
        + "); reinstall monoloc so that the 'migrations' package is shipped"
    )


def alembic_config(database_url: str):  # -> alembic.config.Config
    """An Alembic Config for ``database_url`` using the shipped migrations."""
    from alembic.config import Config

    config = Config()
    # ConfigParser interpolates "%": escape it in the path.
    config.set_main_option("script_location", str(migrations_dir()).replace("%", "%%"))
    config.attributes["database_url"] = database_url
    config.attributes["skip_logging"] = True
    return config


def head_revision() -> str:
    """The newest revision id of the shipped migrations."""
    from alembic.script import ScriptDirectory

    head = ScriptDirectory.from_config(alembic_config("sqlite://")).get_current_head()
    if head is None:
        raise MigrationError(f"no Alembic revisions in {migrations_dir() / 'versions'}")
    return head


def current_revision(database_url: str) -> str | None:
    """The revision the database at ``database_url`` is at (None for an empty database)."""
    from alembic.runtime.migration import MigrationContext
    from sqlalchemy import pool
    from sqlalchemy.exc import SQLAlchemyError

    from monoloc.server.storage.db import _sqlite_file, create_engine_for_url

    db_file = _sqlite_file(database_url) if database_url.startswith("sqlite") else None
    if db_file is not None and not db_file.exists():
        return None  # do not create an empty database just to look at it
    engine = create_engine_for_url(database_url, poolclass=pool.NullPool)
    try:
        with engine.connect() as connection:
            return MigrationContext.configure(connection).get_current_revision()
    except SQLAlchemyError as exc:
        raise MigrationError(f"cannot read {redact_url(database_url)}: {_first_line(exc)}") from exc
    finally:
        engine.dispose()


def upgrade_database(database_url: str, *, take_startup_lock: bool = True) -> None:
    """Bring the database at ``database_url`` to the newest schema (alembic upgrade head).

    Idempotent; creates the SQLite file (and its directory) when missing. Processes
    upgrading the same database take turns on its start-up lock (``storage.db.startup_lock``);
    pass ``take_startup_lock=False`` when the caller already holds it.
    """
    from contextlib import nullcontext

    from alembic import command
    from alembic.util import CommandError
    from sqlalchemy.exc import SQLAlchemyError

    from monoloc.server.storage.db import startup_lock

    try:
        with startup_lock(database_url) if take_startup_lock else nullcontext():
            command.upgrade(alembic_config(database_url), "head")
    except (CommandError, SQLAlchemyError, OSError) as exc:
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else repr(exc)
        raise MigrationError(f"upgrading {redact_url(database_url)} failed: {first_line}") from exc

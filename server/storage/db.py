"""Engine and session set-up. SQLite gets its pragmas on every new connection.

SQLite (the default) runs with ``journal_mode=WAL`` (readers never block the writer),
``foreign_keys=ON`` (cascades and references enforced), ``busy_timeout`` (a writer waits
for the lock instead of failing with "database is locked") and ``synchronous`` from the
settings (see ``monoloc.server.settings`` for the durability trade-off). Any other URL (e.g.
``postgresql+psycopg://...``) is used as is, without pragmas.

Transactions: the pysqlite driver opens a transaction at the first write statement of a
session, so a session that reads and then writes never upgrades a read snapshot (the
case SQLite refuses with SQLITE_BUSY regardless of the timeout); concurrent writers
simply queue on the busy timeout. The repositories therefore do not use SAVEPOINTs
(pysqlite does not support them without extra set-up).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import Engine, create_engine, event
from sqlalchemy.engine import make_url
from sqlalchemy.exc import ArgumentError
from sqlalchemy.orm import Session, sessionmaker

from monoloc.core.errors import InvalidInputError, MonolocError

if TYPE_CHECKING:
    from monoloc.server.settings import Settings

SYNCHRONOUS_LEVELS = ("OFF", "NORMAL", "FULL", "EXTRA")


def libpq_params(url: str) -> dict[str, Any]:
    """psycopg.connect's keyword arguments for a PostgreSQL SQLAlchemy URL (a LISTEN
    connection beside the engine's): host and port from the URL or its query; several
    hosts (``host=h:p&host=h:p``, a failover pair) as libpq's comma lists, with the URL's
    ``target_session_attrs`` (LISTEN needs the primary: a standby refuses it)."""
    parsed = make_url(url)
    params = {k: v for k, v in parsed.query.items() if isinstance(v, str)}
    host, port = params.get("host", parsed.host), params.get("port", parsed.port)
    hosts = parsed.query.get("host")
    if isinstance(hosts, tuple):
        pairs = [h.rsplit(":", 1) if ":" in h else (h, "") for h in hosts]
        host, port = ",".join(h for h, _ in pairs), ",".join(p for _, p in pairs)
    kwargs: dict[str, Any] = dict(
        host=host, port=port, user=parsed.username, password=parsed.password
    )
    kwargs["dbname"] = parsed.database
    if "target_session_attrs" in params:
        kwargs["target_session_attrs"] = params["target_session_attrs"]
    return kwargs


def redact_url(url: str) -> str:
    """The URL with any password masked, for messages and logs."""
    try:
        return make_url(url).render_as_string(hide_password=True)
    except Exception:
        return "<unparseable database URL>"


def _sqlite_file(url: str) -> Path | None:
    """The database file of a SQLite URL, None for in-memory or URI-style databases."""
    database = make_url(url).database
    if not database or database == ":memory:" or database.startswith("file:"):
        return None
    return Path(database)


def create_engine_for_url(
    url: str,
    *,
    sqlite_synchronous: str = "NORMAL",
    busy_timeout_ms: int = 5000,
    **engine_kwargs: Any,
) -> Engine:
    """Create an Engine for ``url``; SQLite connections get WAL, foreign keys, busy timeout
    and ``synchronous``. The SQLite file's directory is created if missing."""
    try:
        parsed = make_url(url)
    except Exception as exc:  # sqlalchemy raises ArgumentError with its own wording
        raise InvalidInputError(f"invalid database URL: {exc}") from exc
    if parsed.get_backend_name() != "sqlite":
        try:
            return create_engine(url, pool_pre_ping=True, **engine_kwargs)
        except (ArgumentError, ImportError) as exc:  # unknown dialect or missing driver
            raise InvalidInputError(f"cannot use database URL {redact_url(url)}: {exc}") from exc

    synchronous = sqlite_synchronous.upper()
    if synchronous not in SYNCHRONOUS_LEVELS:
        raise InvalidInputError(
            f"sqlite_synchronous must be one of {SYNCHRONOUS_LEVELS}, got {sqlite_synchronous!r}"
        )
    if busy_timeout_ms < 0:
        raise InvalidInputError(f"busy_timeout_ms must be >= 0, got {busy_timeout_ms}")
    db_file = _sqlite_file(url)
    if db_file is not None:
        db_file.parent.mkdir(parents=True, exist_ok=True)

    connect_args = dict(engine_kwargs.pop("connect_args", {}))
    connect_args.setdefault("check_same_thread", False)  # sessions move between threads
    connect_args.setdefault("timeout", busy_timeout_ms / 1000.0)
    engine = create_engine(url, connect_args=connect_args, **engine_kwargs)

    @event.listens_for(engine, "connect")
    def _set_sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
        cursor = dbapi_connection.cursor()
        try:
            cursor.execute(f"PRAGMA busy_timeout = {int(busy_timeout_ms)}")
            cursor.execute("PRAGMA journal_mode = WAL").fetchall()
            cursor.execute("PRAGMA foreign_keys = ON")
            cursor.execute(f"PRAGMA synchronous = {synchronous}")
        finally:
            cursor.close()

    return engine


def create_engine_for(settings: Settings) -> Engine:
    """Create the Engine described by ``settings`` (database URL, synchronous, busy timeout)."""
    return create_engine_for_url(
        settings.database_url,
        sqlite_synchronous=settings.sqlite_synchronous,
        busy_timeout_ms=settings.busy_timeout_ms,
    )


def make_session_factory(engine: Engine) -> sessionmaker[Session]:
    """A session factory bound to ``engine``. Objects stay readable after commit."""
    return sessionmaker(bind=engine, expire_on_commit=False)


@contextmanager
def session_scope(factory: sessionmaker[Session]) -> Iterator[Session]:
    """One unit of work: commit when the block succeeds, roll back if it raises."""
    session = factory()
    try:
        yield session
        session.commit()
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


# Any fixed 64-bit number works; this one is "monoloc" in ASCII, so it is recognisable in
# pg_locks and unlikely to collide with another application's advisory locks.
STARTUP_LOCK_KEY = 0x6D6F6E6F6C6F63


class StartupLockTimeoutError(MonolocError):
    """Another process held the database's start-up lock for longer than allowed."""


@contextmanager
def startup_lock(url: str, *, timeout_s: float = 120.0) -> Iterator[None]:
    """Serialise the start-up chores (schema upgrade, bootstrap key) of processes sharing
    the database at ``url``: replicas started together would otherwise race to create the
    same tables or insert the same key, and the loser would exit.

    PostgreSQL: a session-level advisory lock on a connection of its own, released when
    the block ends (or the process dies). SQLite file: an exclusive ``flock`` on
    ``<file>.startup.lock`` beside the database. In-memory SQLite: nothing to share.
    Raises StartupLockTimeoutError if the lock is not had within ``timeout_s``."""
    import time

    from sqlalchemy import pool, text

    parsed = make_url(url)
    if parsed.get_backend_name() == "postgresql":
        engine = create_engine_for_url(url, poolclass=pool.NullPool)
        try:
            with engine.connect() as connection:
                deadline = time.monotonic() + timeout_s
                while not connection.scalar(
                    text("SELECT pg_try_advisory_lock(:key)"), {"key": STARTUP_LOCK_KEY}
                ):
                    connection.rollback()
                    if time.monotonic() > deadline:
                        raise StartupLockTimeoutError(
                            f"another process held the start-up lock of {redact_url(url)} "
                            f"for over {timeout_s:.0f} s"
                        )
                    time.sleep(0.05)
                connection.commit()
                try:
                    yield
                finally:
                    connection.scalar(
                        text("SELECT pg_advisory_unlock(:key)"), {"key": STARTUP_LOCK_KEY}
                    )
                    connection.commit()
        finally:
            engine.dispose()
        return
    db_file = _sqlite_file(url) if parsed.get_backend_name() == "sqlite" else None
    if db_file is None:
        yield
        return
    import fcntl

    db_file.parent.mkdir(parents=True, exist_ok=True)
    with open(db_file.with_name(db_file.name + ".startup.lock"), "a+b") as handle:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise StartupLockTimeoutError(
                        f"another process held the start-up lock of {db_file} "
                        f"for over {timeout_s:.0f} s"
                    ) from None
                time.sleep(0.05)
        try:
            yield
        finally:
            fcntl.flock(handle.fileno(), fcntl.LOCK_UN)

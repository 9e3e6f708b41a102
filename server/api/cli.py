"""`monoloc serve` and `monoloc keys ...` (wired through server/cli.py).

Both act on the database the settings name (``MONOLOC_DATA_DIR`` /
``MONOLOC_DATABASE_URL``), upgrading its schema first, so ``monoloc keys create`` works on
a fresh data directory before the first ``monoloc serve``.
"""

from __future__ import annotations

import enum
from pathlib import Path
from typing import Annotated

import typer

keys_app = typer.Typer(help="API keys: create (printed once), list, revoke.", no_args_is_help=True)

DataDirOption = Annotated[
    Path | None, typer.Option(help="Data directory (default MONOLOC_DATA_DIR or ./data).")
]


def _settings(data_dir: Path | None, **overrides: object):
    from monoloc.server.settings import get_settings

    if data_dir is not None:
        overrides["data_dir"] = data_dir
    return get_settings(**overrides)


def _sessions(data_dir: Path | None):
    from monoloc.server.storage.db import create_engine_for, make_session_factory
    from monoloc.server.storage.migrate import upgrade_database

    settings = _settings(data_dir)
    upgrade_database(settings.database_url)
    return make_session_factory(create_engine_for(settings))


@keys_app.command("create")
def keys_create(
    scope: Annotated[
        list[str],
        typer.Option(help="localize, map:write, metrics or admin (repeat or comma-separate)."),
    ],
    name: Annotated[str, typer.Option(help="Who holds the key, e.g. car1.")],
    map_id: Annotated[
        list[int] | None,
        typer.Option("--map", help="Limit the key to this map id (repeat); default: all maps."),
    ] = None,
    data_dir: DataDirOption = None,
) -> None:
    """Create a key and print it once (only its hash is stored)."""
    from monoloc.server.storage.db import session_scope
    from monoloc.server.storage.keys import create_api_key

    with session_scope(_sessions(data_dir)) as session:
        record, plaintext = create_api_key(session, name, ",".join(scope), map_id or None)
    typer.echo(plaintext)
    typer.echo(
        f"key {record.id} '{record.name}' scopes {','.join(sorted(record.scopes))}: "
        "store it now, it is not shown again",
        err=True,
    )


@keys_app.command("list")
def keys_list(data_dir: DataDirOption = None) -> None:
    """List keys (prefix, name, scopes, revoked or not); never the keys themselves."""
    from monoloc.server.storage.db import session_scope
    from monoloc.server.storage.keys import list_api_keys

    with session_scope(_sessions(data_dir)) as session:
        records = list_api_keys(session)
    for r in records:
        status = f"revoked {r.revoked_at:%Y-%m-%d}" if r.revoked_at else "active"
        typer.echo(
            f"{r.id:4d}  {r.prefix}...  {r.name:<24} {','.join(sorted(r.scopes)):<28} {status}"
        )


@keys_app.command("revoke")
def keys_revoke(key_id: int, data_dir: DataDirOption = None) -> None:
    """Revoke a key by id (see `monoloc keys list`). Running servers refuse it within
    MONOLOC_KEY_CACHE_S (2 s by default)."""
    from monoloc.server.storage.db import session_scope
    from monoloc.server.storage.keys import revoke_api_key

    with session_scope(_sessions(data_dir)) as session:
        record = revoke_api_key(session, key_id)
    typer.echo(
        f"revoked key {record.id} '{record.name}' ({record.prefix}...); running servers "
        "refuse it within MONOLOC_KEY_CACHE_S (2 s by default)"
    )


class HttpProtocol(enum.StrEnum):
    """uvicorn's HTTP/1.1 implementations."""

    auto = "auto"
    httptools = "httptools"
    h11 = "h11"


class EventLoop(enum.StrEnum):
    """uvicorn's event loops."""

    auto = "auto"
    uvloop = "uvloop"
    asyncio = "asyncio"


def serve(
    host: Annotated[str | None, typer.Option(help="Bind address (MONOLOC_HOST).")] = None,
    port: Annotated[int | None, typer.Option(help="Port (MONOLOC_PORT).")] = None,
    data_dir: DataDirOption = None,
    log_level: Annotated[str, typer.Option(help="uvicorn log level.")] = "info",
    workers: Annotated[
        int,
        typer.Option(
            min=1,
            help="Server processes on this port; each is a replica with its own index, kept "
            "current from the database's change log (use PostgreSQL for more than a few).",
        ),
    ] = 1,
    http: Annotated[
        HttpProtocol,
        typer.Option(
            help="HTTP/1.1 parser: httptools (C, installed by the server extra) or h11 (pure "
            "Python: ~25 % more server CPU per request); auto picks httptools when installed.",
        ),
    ] = HttpProtocol.auto,
    loop: Annotated[
        EventLoop,
        typer.Option(help="Event loop: uvloop (the server extra's default) or asyncio."),
    ] = EventLoop.auto,
) -> None:
    """Run the map server: one or more replica processes (--workers) sharing the database."""
    import os

    import uvicorn

    from monoloc.server.api.app import create_app
    from monoloc.server.storage.migrate import upgrade_database

    overrides: dict[str, object] = {}
    if host is not None:
        overrides["host"] = host
    if port is not None:
        overrides["port"] = port
    settings = _settings(data_dir, **overrides)
    if workers == 1:
        uvicorn.run(
            create_app(settings),
            host=settings.host,
            port=settings.port,
            log_level=log_level,
            workers=1,
            http=http.value,
            loop=loop.value,
            timeout_graceful_shutdown=settings.shutdown_grace_s,
        )
        return
    # Worker processes build their app from the environment: pass the resolved settings.
    upgrade_database(settings.database_url)  # once, before the replicas start
    # /metrics of any worker sums every worker's values (prometheus_client's multiprocess
    # mode): their files go to an emptied directory, named to the workers by environment.
    from monoloc.server.api.metrics import MULTIPROC_ENV, prepare_multiprocess_dir

    prepare_multiprocess_dir(
        Path(os.environ.get(MULTIPROC_ENV) or Path(settings.data_dir) / "metrics-multiproc")
    )
    os.environ["MONOLOC_DATA_DIR"] = str(settings.data_dir)
    os.environ["MONOLOC_DATABASE_URL"] = settings.database_url
    uvicorn.run(
        "monoloc.server.api.app:create_app_from_env",
        factory=True,
        host=settings.host,
        port=settings.port,
        log_level=log_level,
        workers=workers,
        http=http.value,
        loop=loop.value,
        timeout_graceful_shutdown=settings.shutdown_grace_s,
    )

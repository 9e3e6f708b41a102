"""`monoloc shards ...`: the operator's side of a map split into shard groups by tile
(monoloc.core.tiles): the nginx router's config written from the tile table, a check of
which tiles a group's database covers, and the copy of a group's tiles of a map from the
map's database into the group's (server/ingest/split.py)."""

from __future__ import annotations

from contextlib import ExitStack
from pathlib import Path
from typing import Annotated

import typer

from monoloc.core.errors import InvalidInputError
from monoloc.core.tiles import TileTable

shards_app = typer.Typer(
    help="A map in shard groups by geographic tile: router config, coverage, split.",
    no_args_is_help=True,
)

TablePath = Annotated[Path, typer.Argument(help="the tile table (JSON, monoloc.core.tiles)")]


LOCALIZE_SLOTS_PER_REPLICA = 4  # a replica's localize lane: 2 worker threads + 2 queued


def render_nginx_config(
    table: TileTable, listen: str = "80", localize_slots: int = LOCALIZE_SLOTS_PER_REPLICA
) -> str:
    """nginx's config routing each request on its ``X-Monoloc-Tile`` header to the
    upstream of the tile's group (``map``), least connections over the group's replicas;
    a localize is retried once on the group's other replica when one is down or sheds it
    (it has no side effects), other requests only when the replica could not be reached.
    A request naming no served tile gets a 400 with a JSON message. Each group's frames
    pass an admission of their own (``max_conns``: ``localize_slots`` frames inside each of
    its replicas; a frame no replica has room for is answered 503 by nginx with
    Retry-After, never proxied, as docker/nginx.conf)."""
    missing = sorted(name for name, group in table.groups.items() if not group.replicas)
    if missing:
        raise InvalidInputError(f"the router needs the replicas of groups {', '.join(missing)}")
    if localize_slots < 1:
        raise InvalidInputError(f"localize slots per replica must be >= 1, not {localize_slots}")
    groups = sorted(table.groups.items())
    tiles = "\n".join(
        f'        "{tile}" shard_{group};' for tile, group in sorted(table.tiles.items())
    )
    localize_tiles = "\n".join(
        f'        "{tile}" shard_{group}_localize;' for tile, group in sorted(table.tiles.items())
    )
    upstreams = "\n\n".join(
        f"    upstream shard_{name} {{\n        least_conn;\n"
        + "".join(
            f"        server {replica} max_fails=3 fail_timeout=5s;\n" for replica in group.replicas
        )
        + "        keepalive 32;\n    }"
        for name, group in groups
    )
    # each group's localize admission: at most localize_slots frames let in to each of its
    # replicas (max_conns, counted across nginx's workers in the zone)
    localize_upstreams = "\n\n".join(
        f"    upstream shard_{name}_localize {{\n        zone shard_{name}_localize 64k;\n"
        "        least_conn;\n"
        + "".join(
            f"        server {replica} max_conns={localize_slots} max_fails=3 fail_timeout=5s;\n"
            for replica in group.replicas
        )
        + "        keepalive 32;\n    }"
        for name, group in groups
    )
    return _NGINX_TEMPLATE.format(
        map_name=table.map_name,
        size=f"{table.scheme.size_m:g}",
        tiles=tiles,
        upstreams=upstreams,
        localize_tiles=localize_tiles,
        localize_upstreams=localize_upstreams,
        listen=listen,
        unknown_tile=_UNKNOWN_TILE,
        shed=_SHED,
        unreachable=_UNREACHABLE,
    )


_UNKNOWN_TILE = (
    '{"error": {"code": "unknown_tile", "message": "X-Monoloc-Tile names no tile of this map"}}'
)
_SHED = (
    '{"error": {"code": "overloaded", "message": "the localize lane of every replica of the '
    'group of the tile is full (nginx admission); retry after Retry-After-Ms"}}'
)
_UNREACHABLE = (
    '{"error": {"code": "bad_gateway", "message": "no replica of the group of the tile '
    'could be reached"}}'
)
_NGINX_TEMPLATE = """\
# nginx in front of the shard groups of map '{map_name}' (tiles of {size} m), written by
# `monoloc shards nginx-config` from the tile table: each request goes to the group of
# the tile its X-Monoloc-Tile header names (the vehicle's ShardedLocalizer sends it), least
# connections over the group's replicas. A localize is free of side effects: it is tried
# once more on the group's other replica when one is down or sheds it. Frames beyond what
# a group's replicas hold are answered 503 here, in C, before any replica sees them.
worker_processes auto;

events {{
    worker_connections 4096;
}}

http {{
    log_format shard '$remote_addr "$request" $status $request_time '
                     'tile=$http_x_monoloc_tile upstream=$upstream_addr '
                     'upstream_status=$upstream_status';
    access_log /dev/stdout shard;

    map $http_x_monoloc_tile $shard_upstream {{
        default "";
{tiles}
    }}

{upstreams}

    # Localize admission per group: each replica lets in its lane (workers + queue
    # depth) of frames (max_conns); a frame of a group none of whose replicas has room
    # finds no upstream to connect to and is answered 503 by @localize_refused, never
    # proxied, while the other groups' frames pass. nginx reads a frame whole before it
    # connects upstream, so a slow upload holds no slot while it arrives.
    map $http_x_monoloc_tile $shard_localize_upstream {{
        default "";
{localize_tiles}
    }}

{localize_upstreams}

    # no room (nginx found no upstream to connect to: $upstream_addr ends in the
    # upstream's name) or no replica reachable
    map $upstream_addr $localize_no_room {{
        ~_localize$ 1;
        default 0;
    }}

    server {{
        listen {listen};
        client_max_body_size 4g;
        default_type application/json;

        proxy_http_version 1.1;
        proxy_set_header Host $host;
        proxy_set_header X-Forwarded-For $proxy_add_x_forwarded_for;
        proxy_set_header X-Forwarded-Proto $scheme;
        proxy_set_header Connection "";
        proxy_read_timeout 120s;
        proxy_ignore_client_abort off;

        if ($shard_upstream = "") {{
            return 400 '{unknown_tile}\\n';
        }}

        # a frame is read whole (in memory, up to 1 MB), then sent to a replica of its
        # tile's group with room for it; tried once more on the group's other replica
        # when one is down or sheds it (a localize has no side effects)
        location ~ ^/v1/maps/[^/]+/localize$ {{
            proxy_pass http://$shard_localize_upstream;
            client_max_body_size 64m;
            client_body_buffer_size 1m;
            proxy_next_upstream error timeout http_503 non_idempotent;
            proxy_next_upstream_tries 2;
            error_page 502 = @localize_refused;
            # nginx logs each frame refused for want of room as "no live upstreams" (an
            # error): the access log has every answer, the error log only what is worse
            error_log /dev/stderr crit;
        }}

        location @localize_refused {{
            if ($localize_no_room) {{
                add_header Retry-After 1 always;
                add_header Retry-After-Ms 50 always;
                return 503 '{shed}';
            }}
            return 502 '{unreachable}';
        }}

        location / {{
            proxy_pass http://$shard_upstream;
            proxy_next_upstream error timeout;
            proxy_request_buffering off;
        }}
    }}
}}
"""


@shards_app.callback()
def _shards() -> None:
    """Shard group commands."""


@shards_app.command("nginx-config")
def nginx_config(
    table_path: TablePath,
    out: Annotated[Path | None, typer.Option(help="write here (default: print)")] = None,
    listen: Annotated[str, typer.Option(help="nginx's listen address")] = "80",
    localize_slots: Annotated[
        int,
        typer.Option(
            help="frames a replica holds (its worker threads + localize queue depth): the "
            "router lets in a group's replicas times this, and answers the next 503"
        ),
    ] = LOCALIZE_SLOTS_PER_REPLICA,
) -> None:
    """Write the router's nginx config for the tile table's groups and replicas."""
    from monoloc.core.tiles import read_tile_table

    text = render_nginx_config(read_tile_table(table_path), listen, localize_slots)
    if out is None:
        typer.echo(text, nl=False)
    else:
        out.write_text(text)
        typer.echo(f"wrote {out}", err=True)


@shards_app.command("coverage")
def coverage(
    table_path: TablePath,
    group: Annotated[str, typer.Option(help="the group whose database this is")],
    database_url: Annotated[
        str | None, typer.Option(help="the group's database (default MONOLOC_DATABASE_URL)")
    ] = None,
) -> None:
    """Entries per tile of the table's map in a group's database; exits 1 when some lie
    in tiles the table gives to another group (or to none)."""
    from monoloc.core.tiles import read_tile_table
    from monoloc.server.cli import _database_url
    from monoloc.server.storage.db import create_engine_for_url, make_session_factory
    from monoloc.server.storage.maps import get_map_by_name
    from monoloc.server.storage.spatial import tile_coverage

    table = read_tile_table(table_path)
    if group not in table.groups:
        raise InvalidInputError(f"group {group!r} is not in {table_path}")
    engine = create_engine_for_url(_database_url(database_url))
    try:
        with make_session_factory(engine)() as session:
            record = get_map_by_name(session, table.map_name)
            counts = tile_coverage(session, record.id, table.scheme)
    finally:
        engine.dispose()
    misplaced = 0
    for tile, n in sorted(counts.items()):
        owner = table.group_of(tile)
        verdict = "ok" if owner == group else f"belongs to {owner or 'no group'}"
        misplaced += 0 if owner == group else n
        typer.echo(f"{tile}\t{n}\t{verdict}")
    if misplaced:
        typer.echo(f"{misplaced} entries outside group {group}'s tiles", err=True)
        raise typer.Exit(1)


_SPLIT_HELP = (
    "Copy the entries of a group's tiles of the table's map from the map's database into "
    "the group's database."
    "\n\n"
    "The destination is migrated first and gets the map if absent: its camera, corner rule, "
    "geo-reference and calibration, the vocabularies and the run records its entries need, "
    "and each entry whose position lies in one of the group's tiles (the tile rule of "
    "`monoloc shards coverage`) with its tags and console image. Entries are written "
    "--batch-rows per transaction, one map version and one change-log row each."
    "\n\n"
    "NOT copied: API keys (create the vehicles' keys in each group's database), the "
    "vehicles' registered cameras (a vehicle registers with each group), jobs, and the "
    "entries of other tiles."
    "\n\n"
    "Idempotent: a rerun after an interruption copies only the entries missing (by source "
    "image hash); a rerun on a complete copy copies nothing. Refuses (one line, exit 1) an "
    "unknown group, a source without the map, a destination map of that name with another "
    "vocabulary, camera or corner rule, and the same database as source and destination."
)


@shards_app.command("split", help=_SPLIT_HELP)
def split(
    table_path: TablePath,
    group: Annotated[str, typer.Option(help="the group whose tiles' entries to copy")],
    from_database: Annotated[
        str, typer.Option(help="the database holding the whole map (SQLAlchemy URL)")
    ],
    to_database: Annotated[
        str, typer.Option(help="the group's database (migrated first; SQLAlchemy URL)")
    ],
    batch_rows: Annotated[int, typer.Option(help="entries per transaction")] = 1000,
) -> None:
    from monoloc.core.tiles import read_tile_table
    from monoloc.server.ingest.report import progress_bar
    from monoloc.server.ingest.split import split_map

    table = read_tile_table(table_path)
    if group not in table.groups:
        raise InvalidInputError(f"group {group!r} is not in {table_path}")
    with ExitStack() as stack:
        bar: list = []

        def update(done: int, total: int) -> None:
            if not bar:  # opened at the first batch: a refusal before it prints one line
                bar.append(stack.enter_context(progress_bar(f"copying {group}")))
            bar[0](done, total)

        summary = split_map(
            table, group, from_database, to_database, batch_rows=batch_rows, progress=update
        )
    verb = "created" if summary.created else "found"
    typer.echo(
        f"map {summary.map_name!r} ({verb} as id {summary.map_id}, version {summary.version}): "
        f"{summary.in_group} entries in group {group}'s tiles, copied {summary.copied}, "
        f"already there {summary.already_there}, skipped outside {summary.outside}; "
        f"runs copied {summary.runs_copied}, vocabularies copied {summary.vocabularies_copied}, "
        f"calibration {summary.calibration}; elapsed {summary.seconds:.1f} s"
    )

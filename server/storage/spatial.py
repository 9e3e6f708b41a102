"""Where a map's entries lie: prior-radius, tile membership and tile coverage queries.

On PostgreSQL with PostGIS (migration 0010) the radius and tile queries run on the GiST
index of ``ST_SetSRID(ST_MakePoint(x_m, y_m), 0)`` (the expression must be written
exactly so for the planner to use it); elsewhere (SQLite, PostgreSQL without PostGIS) on
the (map_id, x_m, y_m) B-tree with a bounding box, the exact test in Python. Both paths
give the same entries, ordered by id.
"""

from __future__ import annotations

import math
from collections import Counter

from sqlalchemy import select, text
from sqlalchemy.orm import Session

from monoloc.core.tiles import TileScheme, tile_id
from monoloc.server.storage.models import Entry

_POINT = "ST_SetSRID(ST_MakePoint(x_m, y_m), 0)"


def has_postgis(session: Session) -> bool:
    """Whether the session's database is PostgreSQL with the postgis extension."""
    if session.get_bind().dialect.name != "postgresql":
        return False
    found = session.execute(text("SELECT 1 FROM pg_extension WHERE extname = 'postgis'"))
    return found.first() is not None


def _in_box(
    session: Session, map_id: int, x_min: float, y_min: float, x_max: float, y_max: float
) -> list[tuple[int, float, float]]:
    """(id, x_m, y_m) of the map's entries in the closed box, from the B-tree."""
    rows = session.execute(
        select(Entry.id, Entry.x_m, Entry.y_m).where(
            Entry.map_id == map_id,
            Entry.x_m >= x_min,
            Entry.x_m <= x_max,
            Entry.y_m >= y_min,
            Entry.y_m <= y_max,
        )
    )
    return [(int(i), float(x), float(y)) for i, x, y in rows]


def entry_ids_within(
    session: Session, map_id: int, x_m: float, y_m: float, radius_m: float
) -> list[int]:
    """Ids of the map's entries within ``radius_m`` of (x_m, y_m) (a prior's disc)."""
    if has_postgis(session):
        rows = session.execute(
            text(
                f"SELECT id FROM entries WHERE map_id = :map_id AND ST_DWithin({_POINT}, "
                "ST_SetSRID(ST_MakePoint(:x, :y), 0), :r) ORDER BY id"
            ),
            {"map_id": map_id, "x": x_m, "y": y_m, "r": radius_m},
        )
        return [int(i) for (i,) in rows]
    box = _in_box(session, map_id, x_m - radius_m, y_m - radius_m, x_m + radius_m, y_m + radius_m)
    return sorted(i for i, x, y in box if math.hypot(x - x_m, y - y_m) <= radius_m)


def entry_ids_in_tile(session: Session, map_id: int, scheme: TileScheme, tile: str) -> list[int]:
    """Ids of the map's entries in ``tile`` (half-open: an entry on the tile's east or
    north edge belongs to the neighbour, as ``TileScheme.tile_of`` has it)."""
    x0, y0, x1, y1 = scheme.bounds(tile)
    if has_postgis(session):
        rows = session.execute(
            text(
                f"SELECT id FROM entries WHERE map_id = :map_id AND {_POINT} && "
                "ST_MakeEnvelope(:x0, :y0, :x1, :y1, 0) AND x_m < :x1 AND y_m < :y1 "
                "ORDER BY id"
            ),
            {"map_id": map_id, "x0": x0, "y0": y0, "x1": x1, "y1": y1},
        )
        return [int(i) for (i,) in rows]
    box = _in_box(session, map_id, x0, y0, x1, y1)
    return sorted(i for i, x, y in box if scheme.tile_of(x, y) == tile)


def tile_coverage(session: Session, map_id: int, scheme: TileScheme) -> dict[str, int]:
    """Entries per tile of the map (tiles without entries left out)."""
    if session.get_bind().dialect.name == "postgresql":
        rows = session.execute(
            text(
                "SELECT floor((x_m - :ox) / :s)::bigint, floor((y_m - :oy) / :s)::bigint, "
                "count(*) FROM entries WHERE map_id = :map_id GROUP BY 1, 2"
            ),
            {
                "map_id": map_id,
                "ox": scheme.origin_x_m,
                "oy": scheme.origin_y_m,
                "s": scheme.size_m,
            },
        )
        return {tile_id(int(ix), int(iy)): int(n) for ix, iy, n in rows}
    rows = session.execute(select(Entry.x_m, Entry.y_m).where(Entry.map_id == map_id))
    return dict(Counter(scheme.tile_of(float(x), float(y)) for x, y in rows))

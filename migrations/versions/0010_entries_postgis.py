"""PostGIS index of the entries' planar positions (PostgreSQL with PostGIS only).

Revision ID: 0010
Revises: 0009
Create Date: 2026-12-02

A map shard's database answers tile membership, prior-radius and coverage queries on its
entries (monoloc.server.storage.spatial). On PostgreSQL where the ``postgis`` extension
is available (Debian: postgresql-NN-postgis-3) this revision creates the extension and a
GiST index on the expression ``ST_SetSRID(ST_MakePoint(x_m, y_m), 0)`` (the map's world
frame: a local engineering frame, SRID 0), so no column duplicates x_m / y_m. Without
PostGIS (SQLite, or a PostgreSQL without the package, or a user who may not create the
extension) the revision logs one line and changes nothing: the spatial queries then use
the (map_id, x_m, y_m) B-tree of revision 0001 and filter the rest in Python.
"""

from __future__ import annotations

import logging

import sqlalchemy as sa
from alembic import op

revision: str = "0010"
down_revision: str | None = "0009"
branch_labels: str | tuple[str, ...] | None = None
depends_on: str | tuple[str, ...] | None = None

INDEX = "ix_entries_position_gist"
log = logging.getLogger("alembic.runtime.migration")


def upgrade() -> None:
    bind = op.get_bind()
    if bind.dialect.name != "postgresql":
        log.info("0010: %s has no PostGIS: entries' spatial index skipped", bind.dialect.name)
        return
    installed = bind.execute(sa.text("SELECT 1 FROM pg_extension WHERE extname = 'postgis'"))
    if installed.first() is None:
        available = bind.execute(
            sa.text("SELECT 1 FROM pg_available_extensions WHERE name = 'postgis'")
        ).first()
        if available is None:
            log.warning("0010: PostGIS is not installed on this server: spatial index skipped")
            return
        try:
            with bind.begin_nested():  # a refused CREATE EXTENSION leaves the rest intact
                bind.execute(sa.text("CREATE EXTENSION IF NOT EXISTS postgis"))
        except sa.exc.DBAPIError as exc:
            log.warning("0010: cannot create the postgis extension (%s): skipped", exc.orig)
            return
    bind.execute(
        sa.text(
            f"CREATE INDEX IF NOT EXISTS {INDEX} ON entries "
            "USING gist ((ST_SetSRID(ST_MakePoint(x_m, y_m), 0)))"
        )
    )


def downgrade() -> None:
    bind = op.get_bind()
    if bind.dialect.name == "postgresql":
        # the extension stays: other schemas of the server may use it
        bind.execute(sa.text(f"DROP INDEX IF EXISTS {INDEX}"))

"""How a map's entries picked their ORB corners.

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-28

``maps.features``: ``monoloc.server.vision.features.selection_rule`` of the ORB settings
the map's entries were described with (JSON), set when a map is created. Every map that
exists before this revision was described with ORB's own rule (the strongest corners of
the whole image): the upgrade says so, ``{"rule": "strongest"}``; the grid came with it.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0007"
down_revision: str | None = "0006"
branch_labels: str | tuple[str, ...] | None = None
depends_on: str | tuple[str, ...] | None = None


def upgrade() -> None:
    with op.batch_alter_table("maps") as batch:
        batch.add_column(sa.Column("features", sa.JSON(), nullable=True))
    maps = sa.table("maps", sa.column("features", sa.JSON()))
    op.execute(maps.update().values(features={"rule": "strongest"}))


def downgrade() -> None:
    with op.batch_alter_table("maps") as batch:
        batch.drop_column("features")

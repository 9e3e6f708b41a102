"""API keys limited to some maps (tenants).

Revision ID: 0008
Revises: 0007
Create Date: 2026-12-02

``api_keys.maps``: the ids of the maps a key may touch (JSON list), NULL for every map.
Every key that exists before this revision saw every map: the upgrade leaves them NULL.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0008"
down_revision: str | None = "0007"
branch_labels: str | tuple[str, ...] | None = None
depends_on: str | tuple[str, ...] | None = None


def upgrade() -> None:
    with op.batch_alter_table("api_keys") as batch:
        batch.add_column(sa.Column("maps", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("api_keys") as batch:
        batch.drop_column("maps")

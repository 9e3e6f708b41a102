"""A run's registration to its map.

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-27

``runs.registration``: how the run was registered to the map before its entries were
built (JSON, ``monoloc.core.registration.RunCorrection.summary``; NULL when it was not).
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0006"
down_revision: str | None = "0005"
branch_labels: str | tuple[str, ...] | None = None
depends_on: str | tuple[str, ...] | None = None


def upgrade() -> None:
    with op.batch_alter_table("runs") as batch:
        batch.add_column(sa.Column("registration", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("runs") as batch:
        batch.drop_column("registration")

"""The fleet: a per-map change log that replicas apply as deltas, and job leases.

Revision ID: 0002
Revises: 0001
Create Date: 2026-05-20

``map_changes``: one row per map version (entry added, deleted, re-tagged, VLAD
rewritten, vocabulary changed). Maps that already have a version get one ``vocabulary``
row at their current version, so a replica that sees an older version rebuilds once and
then follows the log. ``jobs``: ``lease_owner``, ``lease_expires_at``, ``attempts``.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | tuple[str, ...] | None = None
depends_on: str | tuple[str, ...] | None = None


def upgrade() -> None:
    op.create_table(
        "map_changes",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("map_id", sa.Integer(), nullable=False),
        sa.Column("version", sa.Integer(), nullable=False),
        sa.Column("kind", sa.String(length=16), nullable=False),
        sa.Column("entry_id", sa.Integer(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.CheckConstraint(
            "kind IN ('add', 'delete', 'retag', 'vlad', 'vocabulary')",
            name=op.f("ck_map_changes_kind"),
        ),
        sa.ForeignKeyConstraint(
            ["map_id"],
            ["maps.id"],
            name=op.f("fk_map_changes_map_id_maps"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_map_changes")),
        sa.UniqueConstraint("map_id", "version", name=op.f("uq_map_changes_map_id_version")),
    )
    op.execute(
        "INSERT INTO map_changes (map_id, version, kind, created_at) "
        "SELECT id, version, 'vocabulary', updated_at FROM maps WHERE version > 0"
    )
    with op.batch_alter_table("jobs") as batch:
        batch.add_column(sa.Column("lease_owner", sa.String(length=128), nullable=True))
        batch.add_column(sa.Column("lease_expires_at", sa.DateTime(timezone=True), nullable=True))
        batch.add_column(
            sa.Column("attempts", sa.Integer(), server_default=sa.text("0"), nullable=False)
        )
        batch.create_index(batch.f("ix_jobs_lease_expires_at"), ["lease_expires_at"])


def downgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.drop_index(batch.f("ix_jobs_lease_expires_at"))
        batch.drop_column("attempts")
        batch.drop_column("lease_expires_at")
        batch.drop_column("lease_owner")
    op.drop_table("map_changes")

"""Vehicles' cameras, registered once and named by id in queries.

Revision ID: 0009
Revises: 0008
Create Date: 2026-12-02

``cameras``: a fleet camera's pinhole intrinsics (px) with its image size, its lens
distortion (ROS CameraInfo's model name and D, NULL for a pinhole) and the API key that
registered it (SET NULL when that key's row goes). A new table: nothing to convert.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0009"
down_revision: str | None = "0008"
branch_labels: str | tuple[str, ...] | None = None
depends_on: str | tuple[str, ...] | None = None


def upgrade() -> None:
    op.create_table(
        "cameras",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=128), nullable=False),
        sa.Column("fx", sa.Double(), nullable=False),
        sa.Column("fy", sa.Double(), nullable=False),
        sa.Column("cx", sa.Double(), nullable=False),
        sa.Column("cy", sa.Double(), nullable=False),
        sa.Column("width_px", sa.Integer(), nullable=False),
        sa.Column("height_px", sa.Integer(), nullable=False),
        sa.Column("distortion_model", sa.String(length=32), nullable=True),
        sa.Column("distortion", sa.JSON(), nullable=True),
        sa.Column("key_id", sa.Integer(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.CheckConstraint("fx > 0 AND fy > 0", name=op.f("ck_cameras_focal_positive")),
        sa.CheckConstraint("width_px > 0 AND height_px > 0", name=op.f("ck_cameras_size_positive")),
        sa.ForeignKeyConstraint(
            ["key_id"],
            ["api_keys.id"],
            name=op.f("fk_cameras_key_id_api_keys"),
            ondelete="SET NULL",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_cameras")),
    )
    op.create_index(op.f("ix_cameras_key_id"), "cameras", ["key_id"], unique=False)


def downgrade() -> None:
    op.drop_index(op.f("ix_cameras_key_id"), table_name="cameras")
    op.drop_table("cameras")

"""Entry images: a small JPEG of each reference image, for the operator's console.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-23

``entry_images``: one row per entry (deleted with it): the reference image downscaled to
at most ``BuildConfig.preview_max_side_px`` (grey JPEG), its size, and the keypoints the
entry does not keep because they got no 3D point (so the console can show both kinds).
Entries added before this revision have no row: their page says the image is not stored.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels: str | tuple[str, ...] | None = None
depends_on: str | tuple[str, ...] | None = None


def upgrade() -> None:
    op.create_table(
        "entry_images",
        sa.Column("entry_id", sa.Integer(), nullable=False),
        sa.Column("jpeg", sa.LargeBinary(), nullable=False),
        sa.Column("width_px", sa.Integer(), nullable=False),
        sa.Column("height_px", sa.Integer(), nullable=False),
        sa.Column("keypoints_without_point_px", sa.LargeBinary(), nullable=False),
        sa.CheckConstraint(
            "width_px > 0 AND height_px > 0", name=op.f("ck_entry_images_size_positive")
        ),
        sa.ForeignKeyConstraint(
            ["entry_id"],
            ["entries.id"],
            name=op.f("fk_entry_images_entry_id_entries"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("entry_id", name=op.f("pk_entry_images")),
    )


def downgrade() -> None:
    op.drop_table("entry_images")

"""Geo-referenced maps and ROS bag runs.

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-23

``maps.geo_reference``: the map's geographic reference (JSON, NULL when the map is not
geo-referenced; ``monoloc.core.geo.GeoReference.to_dict``). ``runs.source_format``
also accepts ``rosbag``.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0005"
down_revision: str | None = "0004"
branch_labels: str | tuple[str, ...] | None = None
depends_on: str | tuple[str, ...] | None = None

_OLD_FORMATS = "source_format IN ('kitti', 'tum', 'single', 'colmap', 'kapture')"
_NEW_FORMATS = "source_format IN ('kitti', 'tum', 'single', 'colmap', 'kapture', 'rosbag')"


def upgrade() -> None:
    with op.batch_alter_table("maps") as batch:
        batch.add_column(sa.Column("geo_reference", sa.JSON(), nullable=True))
    with op.batch_alter_table("runs") as batch:
        batch.drop_constraint(batch.f("ck_runs_source_format"), type_="check")
        batch.create_check_constraint(batch.f("ck_runs_source_format"), _NEW_FORMATS)


def downgrade() -> None:
    op.execute("DELETE FROM runs WHERE source_format = 'rosbag'")
    with op.batch_alter_table("runs") as batch:
        batch.drop_constraint(batch.f("ck_runs_source_format"), type_="check")
        batch.create_check_constraint(batch.f("ck_runs_source_format"), _OLD_FORMATS)
    with op.batch_alter_table("maps") as batch:
        batch.drop_column("geo_reference")

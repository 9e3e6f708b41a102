"""Runs imported from the field's formats: ``source_format`` may be ``colmap`` (a COLMAP
sparse model) or ``kapture`` (a kapture dataset).

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-23
"""

from __future__ import annotations

from alembic import op

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | tuple[str, ...] | None = None
depends_on: str | tuple[str, ...] | None = None

_OLD = "source_format IN ('kitti', 'tum', 'single')"
_NEW = "source_format IN ('kitti', 'tum', 'single', 'colmap', 'kapture')"


def _replace_check(condition: str) -> None:
    # SQLite cannot alter a constraint: batch mode copies the table there ("auto"), and
    # alters it in place on PostgreSQL (a copy there would have to drop the primary key
    # that entries and jobs refer to).
    with op.batch_alter_table("runs") as batch:
        batch.drop_constraint(batch.f("ck_runs_source_format"), type_="check")
        batch.create_check_constraint(batch.f("ck_runs_source_format"), condition)


def upgrade() -> None:
    _replace_check(_NEW)


def downgrade() -> None:
    op.execute("DELETE FROM runs WHERE source_format IN ('colmap', 'kapture')")
    _replace_check(_OLD)

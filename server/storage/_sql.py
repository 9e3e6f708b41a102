"""Small SQL helpers shared by the repositories."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from sqlalchemy import insert
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from monoloc.core.errors import ConflictError


def insert_or_ignore(
    session: Session, model: Any, values: dict[str, Any], conflict_columns: Sequence[str]
) -> int | None:
    """INSERT a row unless it violates the unique key ``conflict_columns``.

    Returns the new primary key, or None when a row with the same key exists (already, or
    committed concurrently). Uses ``ON CONFLICT DO NOTHING`` (SQLite, PostgreSQL), so a
    duplicate never aborts the caller's transaction. Other dialects fall back to a plain
    INSERT whose IntegrityError becomes a ConflictError.
    """
    dialect = session.get_bind().dialect.name
    if dialect == "sqlite":
        from sqlalchemy.dialects.sqlite import insert as dialect_insert
    elif dialect == "postgresql":
        from sqlalchemy.dialects.postgresql import insert as dialect_insert
    else:
        try:
            result = session.execute(insert(model).values(**values).returning(model.id))
        except IntegrityError as exc:
            raise ConflictError(f"{model.__tablename__}: duplicate {conflict_columns}") from exc
        return int(result.scalar_one())
    stmt = (
        dialect_insert(model)
        .values(**values)
        .on_conflict_do_nothing(index_elements=list(conflict_columns))
        .returning(model.id)
    )
    new_id = session.execute(stmt).scalar_one_or_none()
    return None if new_id is None else int(new_id)

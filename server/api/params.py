"""Path and query parameters shared by the routes, with their bounds in the OpenAPI
description: a database id is a positive signed 64-bit integer, so an id outside
1..2^63-1 is refused with 422 before it reaches the database driver (which cannot even
represent it), and paging offsets stay within the same range."""

from __future__ import annotations

from typing import Annotated

from fastapi import Path, Query

DB_ID_MAX = 2**63 - 1  # SQLite INTEGER / PostgreSQL BIGINT


def id_path(what: str) -> Path:
    return Path(ge=1, le=DB_ID_MAX, description=f"The {what}'s id (1 to 2^63 - 1).")


MapId = Annotated[int, id_path("map")]
EntryId = Annotated[int, id_path("entry")]
RunId = Annotated[int, id_path("run")]
JobId = Annotated[int, id_path("job")]
KeyId = Annotated[int, id_path("API key")]
Offset = Annotated[int, Query(ge=0, le=DB_ID_MAX, description="Items to skip.")]
Limit = Annotated[int, Query(ge=1, le=1000, description="Items per page.")]


def is_db_id(value: int) -> bool:
    """Whether ``value`` can be a database id (the WebSocket route checks it by hand)."""
    return 1 <= value <= DB_ID_MAX

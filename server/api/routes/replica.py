"""``GET /v1/maps/{map_id}/replica`` (admin): what this replica holds of a map in memory,
beside what the database holds, so an operator (and the fleet tests) can check that a
replica has caught up."""

from __future__ import annotations

import hashlib

import anyio.to_thread
import numpy as np
from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy import select

from monoloc.server.api.convert import AUTH_ERRORS, error_responses
from monoloc.server.api.deps import AdminKey, StateDep
from monoloc.server.api.guard import GuardedRoute
from monoloc.server.api.params import MapId
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.models import Entry

router = APIRouter(prefix="/v1/maps/{map_id}", tags=["maps"], route_class=GuardedRoute)


class ReplicaSide(BaseModel):
    map_version: int
    entries: int
    entry_ids_sha256: str = Field(description="sha256 of the sorted entry ids (int64 LE).")


_SIDE = {"map_version": 4013, "entries": 3860, "entry_ids_sha256": "9f86d08188...b0f00a08"}


class ReplicaState(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={"examples": [{"replica": _SIDE, "database": _SIDE, "in_sync": True}]}
    )
    replica: ReplicaSide = Field(description="This process's index of the map.")
    database: ReplicaSide = Field(description="The map in the database, read now.")
    in_sync: bool


def _digest(ids) -> str:
    return hashlib.sha256(np.sort(np.asarray(ids, dtype="<i8")).tobytes()).hexdigest()


def _state(state, map_id: int) -> ReplicaState:
    runtime = state.registry.get(map_id)
    ids = runtime.index.entry_ids()
    mine = ReplicaSide(map_version=runtime.version, entries=len(ids), entry_ids_sha256=_digest(ids))
    with session_scope(state.sessions) as session:
        version = maps_repo.get_map(session, map_id).version
        db_ids = list(session.scalars(select(Entry.id).where(Entry.map_id == map_id)))
    db = ReplicaSide(map_version=version, entries=len(db_ids), entry_ids_sha256=_digest(db_ids))
    return ReplicaState(replica=mine, database=db, in_sync=mine == db)


@router.get(
    "/replica",
    response_model=ReplicaState,
    responses={**AUTH_ERRORS, **error_responses(404, 422)},
    summary="This replica's index of the map vs the database",
)
async def replica_state(map_id: MapId, state: StateDep, _key: AdminKey) -> ReplicaState:
    """The map version and entry ids indexed by this process, and the database's."""
    return await anyio.to_thread.run_sync(_state, state, map_id)

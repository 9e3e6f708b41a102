"""Read-your-writes across replicas: a write answers the map version it produced (the
``map_version`` field or the ``X-Map-Version`` header); a localize request sending
``X-Min-Map-Version`` is answered from a map at least that new. The replica catches up
from the database's change log at once (the write is committed before it is answered),
and waits a little for a version not in the database yet; past the wait it answers 503
``stale_replica`` with ``Retry-After`` instead of an answer from an older map."""

from __future__ import annotations

import time

import anyio
import anyio.to_thread

from monoloc.server.api.admission import OverloadedError
from monoloc.server.map_registry import MapRegistry

MIN_VERSION_HEADER = "X-Min-Map-Version"
MAP_VERSION_HEADER = "X-Map-Version"


class StaleReplicaError(OverloadedError):
    """This replica's map is older than the request's minimum version after the wait."""

    code = "stale_replica"


async def await_map_version(
    registry: MapRegistry, map_id: int, min_version: int | None, wait_s: float
) -> None:
    """Return once the registry holds ``map_id`` at ``min_version`` or newer (None: at
    once); StaleReplicaError after ``wait_s``; NotFoundError if the map is gone."""
    if min_version is None:
        return
    deadline = time.monotonic() + wait_s
    while True:
        version = registry.version(map_id)
        if version is not None and version >= min_version:
            return
        runtime = await anyio.to_thread.run_sync(registry.catch_up, map_id)
        if runtime.version >= min_version:
            return
        if time.monotonic() >= deadline:
            raise StaleReplicaError(
                f"map {map_id} is at version {runtime.version} on this replica, the request "
                f"needs {min_version} or newer (not in the database yet?)",
                1,
            )
        await anyio.sleep(min(0.05, max(0.0, deadline - time.monotonic())))

"""A replica's short memory of the API keys it has verified.

Every costly request names its key; verifying it is a database query. A vehicle sends
ten frames a second, so without a memory each frame costs the replica a round trip to
the database and the database one query per frame of the whole fleet, the only
database work left on the localize path. A key verified within the last ``ttl_s`` is
taken from here instead (its record, scopes included).

Revocation: the replica that revokes a key forgets it at once; another replica refuses
it at the latest ``ttl_s`` later (its memory of the key expires). ``ttl_s`` = 0 turns
the memory off. While the database cannot be reached (a PostgreSQL failover: 2-5 s on
loopback, tests/shards), a key whose memory expired less than ``stale_s`` ago is still
taken (:meth:`KeyCache.get_stale`): no key can be revoked meanwhile either. Only keys
that verified are kept (an unknown key is looked up every time, so guessing keys cannot
fill the memory), at most ``max_keys`` of them.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict

from sqlalchemy.exc import InterfaceError, OperationalError

from monoloc.server.storage.keys import hash_api_key
from monoloc.server.storage.records import ApiKeyRecord

# What the driver raises when the database cannot be reached (down, restarting, failing
# over): the caches below answer from memory then, for a bounded time.
DATABASE_UNREACHABLE = (OperationalError, InterfaceError)
STALE_IF_UNREACHABLE_S = 60.0


class KeyCache:
    def __init__(
        self, ttl_s: float, max_keys: int = 10_000, stale_s: float = STALE_IF_UNREACHABLE_S
    ) -> None:
        self.ttl_s = ttl_s
        self.max_keys = max_keys
        self.stale_s = stale_s
        self._items: OrderedDict[str, tuple[float, ApiKeyRecord]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, presented: str) -> ApiKeyRecord | None:
        """The record of ``presented`` if it verified within ``ttl_s``; else None."""
        if self.ttl_s <= 0:
            return None
        digest = hash_api_key(presented)
        with self._lock:
            found = self._items.get(digest)
            if found is None:
                return None
            if time.monotonic() >= found[0]:
                if time.monotonic() >= found[0] + self.stale_s:
                    del self._items[digest]
                return None
            return found[1]

    def get_stale(self, presented: str) -> ApiKeyRecord | None:
        """The record of ``presented`` if its memory expired less than ``stale_s`` ago
        (or has not): for a request that found the database unreachable."""
        digest = hash_api_key(presented)
        with self._lock:
            found = self._items.get(digest)
            if found is None or time.monotonic() >= found[0] + self.stale_s:
                return None
            return found[1]

    def put(self, presented: str, record: ApiKeyRecord) -> None:
        """Remember a key that just verified against the database."""
        if self.ttl_s <= 0:
            return
        digest = hash_api_key(presented)
        with self._lock:
            self._items.pop(digest, None)
            self._items[digest] = (time.monotonic() + self.ttl_s, record)
            while len(self._items) > self.max_keys:
                self._items.popitem(last=False)  # the oldest verification

    def forget(self, key_id: int) -> None:
        """Drop a key (revoked through this replica)."""
        with self._lock:
            for digest in [d for d, (_, r) in self._items.items() if r.id == key_id]:
                del self._items[digest]

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)

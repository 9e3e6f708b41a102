"""A replica's short memory of the registered cameras its frames name.

A vehicle names its camera (``camera_id``) in every frame, ten a second: reading the
camera from the database each time would put a query back on the localize path that
the key cache took off it. A camera read within the last ``ttl_s`` is taken from here.
Cameras never change once registered; a deleted one is forgotten at once by the
replica that deleted it and ``ttl_s`` later by the others. ``ttl_s`` = 0 turns the
memory off. Unknown ids are never kept. While the database cannot be reached, a camera
read less than ``ttl_s`` + ``stale_s`` ago is still taken (as the key cache does).
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable

from monoloc.server.api.key_cache import DATABASE_UNREACHABLE, STALE_IF_UNREACHABLE_S
from monoloc.server.storage.cameras import CameraRecord


class CameraCache:
    def __init__(
        self, ttl_s: float, max_cameras: int = 10_000, stale_s: float = STALE_IF_UNREACHABLE_S
    ) -> None:
        self.ttl_s = ttl_s
        self.max_cameras = max_cameras
        self.stale_s = stale_s
        self._items: OrderedDict[int, tuple[float, CameraRecord]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, camera_id: int, load: Callable[[int], CameraRecord]) -> CameraRecord:
        """The camera ``camera_id``, from memory if read within ``ttl_s``, else
        ``load(camera_id)`` (which raises NotFoundError for an unknown id)."""
        now = time.monotonic()
        with self._lock:
            found = self._items.get(camera_id)
            if found is not None and now < found[0]:
                return found[1]
        try:
            record = load(camera_id)
        except DATABASE_UNREACHABLE:
            if found is None or now >= found[0] + self.stale_s:
                raise
            return found[1]
        if self.ttl_s > 0:
            with self._lock:
                self._items.pop(camera_id, None)
                self._items[camera_id] = (now + self.ttl_s, record)
                while len(self._items) > self.max_cameras:
                    self._items.popitem(last=False)
        return record

    def forget(self, camera_id: int) -> None:
        with self._lock:
            self._items.pop(camera_id, None)

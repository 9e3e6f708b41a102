"""The replica's key and camera memories while the database cannot be reached (a
PostgreSQL failover): a key or camera whose memory expired less than ``stale_s`` ago is
still taken, an older or unknown one is not, and a database that answers is asked as
before (tests/shards/test_shard_drive.py has the failover itself)."""

from __future__ import annotations

from datetime import UTC, datetime

import pytest
from sqlalchemy.exc import OperationalError

from monoloc.core.camera import KITTI_CAM0
from monoloc.server.api import camera_cache, key_cache
from monoloc.server.api.camera_cache import CameraCache
from monoloc.server.api.key_cache import KeyCache
from monoloc.server.storage.cameras import CameraRecord
from monoloc.server.storage.records import ApiKeyRecord

NOW = datetime.now(UTC)


class Clock:
    """The caches' ``time`` module, advanced by hand."""

    def __init__(self) -> None:
        self.now_s = 1000.0

    def monotonic(self) -> float:
        return self.now_s


@pytest.fixture
def clock(monkeypatch) -> Clock:
    clock = Clock()
    monkeypatch.setattr(key_cache, "time", clock)
    monkeypatch.setattr(camera_cache, "time", clock)
    return clock


def _unreachable(_camera_id: int) -> CameraRecord:
    raise OperationalError("SELECT", {}, Exception("connection refused"))


def _key(key_id: int) -> ApiKeyRecord:
    return ApiKeyRecord(key_id, f"k{key_id}", "mlk_AAAA", frozenset({"localize"}), NOW, None)


def test_an_expired_key_is_stale_for_stale_s_then_gone(clock):
    cache = KeyCache(ttl_s=2.0, stale_s=60.0)
    cache.put("mlk_one", _key(1))
    clock.now_s += 1.9
    assert cache.get("mlk_one").id == 1
    clock.now_s += 0.2
    assert cache.get("mlk_one") is None  # expired: the database is asked again
    assert cache.get_stale("mlk_one").id == 1  # ... and if it cannot answer, still good
    assert cache.get_stale("mlk_other") is None
    clock.now_s += 60.0
    assert cache.get_stale("mlk_one") is None
    assert cache.get("mlk_one") is None and len(cache) == 0
    off = KeyCache(ttl_s=0.0)
    off.put("mlk_one", _key(1))
    assert off.get_stale("mlk_one") is None  # no memory, no stale memory


def test_a_camera_read_lately_answers_while_the_database_is_unreachable(clock):
    cache = CameraCache(ttl_s=2.0, stale_s=60.0)
    loads = []

    def load(camera_id: int) -> CameraRecord:
        loads.append(camera_id)
        return CameraRecord(camera_id, "front", KITTI_CAM0, None, NOW)

    assert cache.get(3, load).id == 3
    clock.now_s += 2.1
    assert cache.get(3, load).id == 3 and loads == [3, 3]  # expired: read again
    clock.now_s += 2.1
    assert cache.get(3, _unreachable).id == 3  # expired, unreachable: the memory
    with pytest.raises(OperationalError):
        cache.get(4, _unreachable)  # never read: the error stands
    clock.now_s += 62.0
    with pytest.raises(OperationalError):
        cache.get(3, _unreachable)  # past stale_s

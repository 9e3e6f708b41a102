"""The server's live memory of its maps: vocabulary, retrieval index and entry cache.

One ``MapRegistry`` per process. A map's runtime is loaded on first use (or at start-up
by ``load_all``): its index comes from the index file when that file is intact and
stamped with the database's map version, and is otherwise rebuilt from the database and
re-saved; it is never served empty. Edits made through the registry (after their
database commit) reach the index at once. Edits made by another process (a CLI
ingestion next to a running server) are noticed by a cheap version check, at most once
per ``version_check_s`` per map, and trigger a rebuild.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import NotFoundError
from monoloc.core.measurement import MeasurementModel
from monoloc.core.prior import RetrievalPrior
from monoloc.server.index.persist import IndexFileError, load_index, save_index
from monoloc.server.index.retrieval import IndexConfig, RetrievalIndex
from monoloc.server.localize import (
    LocalizationResult,
    LocalizeConfig,
    ReferenceEntry,
    localize_frame,
)
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.records import MapRecord
from monoloc.server.vision.vocabulary import Vocabulary

log = logging.getLogger(__name__)


class EntryCache:
    """LRU cache of reference entries (descriptors + 3D points) loaded from the database."""

    def __init__(self, loader: Callable[[Sequence[int]], list[ReferenceEntry]], capacity: int):
        self._loader = loader
        self._capacity = capacity
        self._items: OrderedDict[int, ReferenceEntry] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, entry_ids: Sequence[int]) -> list[ReferenceEntry]:
        with self._lock:
            found = {i: self._items[i] for i in entry_ids if i in self._items}
            for i in found:
                self._items.move_to_end(i)
        missing = [i for i in entry_ids if i not in found]
        if missing:
            loaded = self._loader(missing)
            with self._lock:
                for entry in loaded:
                    found[entry.entry_id] = entry
                    self._items[entry.entry_id] = entry
                while len(self._items) > self._capacity:
                    self._items.popitem(last=False)
        return [found[i] for i in entry_ids if i in found]

    def __contains__(self, entry_id: int) -> bool:
        with self._lock:
            return entry_id in self._items

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)

    def discard(self, entry_ids: Sequence[int]) -> None:
        with self._lock:
            for i in entry_ids:
                self._items.pop(i, None)


@dataclass
class MapRuntime:
    """One map as the server holds it in memory."""

    record: MapRecord
    vocabulary: Vocabulary
    index: RetrievalIndex
    cache: EntryCache
    version: int
    checked_at: float

    @property
    def measurement_model(self) -> MeasurementModel:
        if self.record.calibration:
            return MeasurementModel.from_dict(self.record.calibration)
        return MeasurementModel()


class MapRegistry:
    """All maps' runtimes; thread-safe."""

    def __init__(
        self,
        session_factory: sessionmaker[Session],
        index_dir: Path,
        index_config: IndexConfig | None = None,
        cache_entries: int = 20_000,
        version_check_s: float = 1.0,
    ) -> None:
        self._sessions = session_factory
        self._index_dir = Path(index_dir)
        self._index_config = index_config or IndexConfig()
        self._cache_entries = cache_entries
        self._version_check_s = version_check_s
        self._maps: dict[int, MapRuntime] = {}
        self._lock = threading.RLock()
        self._load_locks: dict[int, threading.Lock] = {}

    def index_path(self, map_id: int) -> Path:
        return self._index_dir / f"map_{map_id}.index.npz"

    # ---- loading --------------------------------------------------------------------
    def _lookup(self, ids: Sequence[int]) -> list[ReferenceEntry]:
        """The entries that still exist (an entry deleted in the database may linger in
        the index until ``entries_removed`` or the next version check: it is skipped)."""
        with session_scope(self._sessions) as session:
            try:
                rows = entries_repo.get_entry_data(session, list(ids))
            except NotFoundError:
                rows = []
                for entry_id in ids:
                    try:
                        rows.extend(entries_repo.get_entry_data(session, [entry_id]))
                    except NotFoundError:
                        continue
        return [
            ReferenceEntry(
                entry_id=r.id,
                T_world_from_cam=np.asarray(r.T_world_from_cam),
                descriptors=np.asarray(r.descriptors),
                points_cam=np.asarray(r.points_cam),
                tags=r.summary.tags,
            )
            for r in rows
        ]

    def _build(self, map_id: int) -> MapRuntime:
        with session_scope(self._sessions) as session:
            record = maps_repo.get_map(session, map_id)
            vocab_record = maps_repo.get_vocabulary(session, record.vocabulary_id)
            vocabulary = Vocabulary.from_centres(
                np.asarray(vocab_record.centres), vocab_record.description
            )
            path = self.index_path(map_id)
            try:
                index = load_index(path, record.version, self._index_config)
                log.info("map %s: index loaded from %s (%d entries)", map_id, path, len(index))
            except IndexFileError as exc:
                log.warning("map %s: %s; rebuilding from the database", map_id, exc)
                index = RetrievalIndex(self._index_config)
                for batch in entries_repo.iter_map_vectors(session, map_id):
                    index.add(batch.entry_ids, batch.codes, batch.vlads, batch.planar)
                save_index(path, index, record.version)
        cache = EntryCache(self._lookup, self._cache_entries)
        self._warm(cache, index.entry_ids(), len(index))
        return MapRuntime(record, vocabulary, index, cache, record.version, time.monotonic())

    def _warm(self, cache: EntryCache, entry_ids: np.ndarray, map_size: int) -> None:
        """Load entries into the cache when the whole map fits in it: a query then reads
        no database rows (a cold lookup of ten entries is a visible share of a query;
        bench/localize.py reports the lookup stage)."""
        if map_size > self._cache_entries:
            return
        ids = np.asarray(entry_ids, dtype=np.int64).tolist()
        for start in range(0, len(ids), 512):
            cache.get(ids[start : start + 512])

    def get(self, map_id: int) -> MapRuntime:
        """The map's runtime, loading or refreshing it if needed (NotFoundError if gone)."""
        with self._lock:
            runtime = self._maps.get(map_id)
            load_lock = self._load_locks.setdefault(map_id, threading.Lock())
        if runtime is not None and time.monotonic() - runtime.checked_at < self._version_check_s:
            return runtime
        with load_lock:
            with self._lock:
                runtime = self._maps.get(map_id)
            if runtime is not None:
                with session_scope(self._sessions) as session:
                    record = maps_repo.get_map(session, map_id)
                if record.version == runtime.version:
                    runtime.record, runtime.checked_at = record, time.monotonic()
                    return runtime
                log.info("map %s changed outside this process; reloading", map_id)
            runtime = self._build(map_id)
            with self._lock:
                self._maps[map_id] = runtime
            return runtime

    def load_all(self) -> int:
        """Load every map (start-up). Returns how many were loaded."""
        with session_scope(self._sessions) as session:
            ids = [m.id for m in maps_repo.list_maps(session)]
        for map_id in ids:
            self.get(map_id)
        return len(ids)

    def loaded(self) -> dict[int, int]:
        """Map id -> number of indexed entries, for the maps in memory."""
        with self._lock:
            return {map_id: len(rt.index) for map_id, rt in self._maps.items()}

    # ---- edits (call after the database commit) -------------------------------------
    def entries_added(
        self, map_id: int, entry_ids, codes, vlads, poses_world, new_version: int
    ) -> None:
        runtime = self._maps.get(map_id)
        if runtime is None:
            return  # loaded from the database on first use
        runtime.index.add(entry_ids, codes, vlads, poses_world)
        runtime.cache.discard(list(np.asarray(entry_ids).tolist()))  # replaced entries
        runtime.version = new_version
        # Read the new entries now, on the adding thread, not on a vehicle's first query.
        self._warm(runtime.cache, entry_ids, len(runtime.index))

    def entries_removed(self, map_id: int, entry_ids: Sequence[int], new_version: int) -> None:
        runtime = self._maps.get(map_id)
        if runtime is None:
            return
        runtime.index.remove(entry_ids)
        runtime.cache.discard(entry_ids)
        runtime.version = new_version

    def entry_retagged(self, map_id: int, entry_id: int) -> None:
        runtime = self._maps.get(map_id)
        if runtime is not None:
            runtime.cache.discard([entry_id])
            self._warm(runtime.cache, [entry_id], len(runtime.index))

    def forget(self, map_id: int, delete_file: bool = False) -> None:
        """Drop a map from memory (deleted, or its vocabulary changed)."""
        with self._lock:
            self._maps.pop(map_id, None)
        if delete_file:
            self.index_path(map_id).unlink(missing_ok=True)

    def persist(self, map_id: int | None = None) -> None:
        """Write the index file of one map (or of all loaded maps)."""
        with self._lock:
            targets = [map_id] if map_id is not None else list(self._maps)
        for mid in targets:
            runtime = self._maps.get(mid)
            if runtime is not None:
                save_index(self.index_path(mid), runtime.index, runtime.version)

    # ---- queries ----------------------------------------------------------------------
    def localize(
        self,
        map_id: int,
        image_gray: np.ndarray,
        config: LocalizeConfig,
        rng: np.random.Generator,
        intrinsics: CameraIntrinsics | None = None,
        prior: RetrievalPrior | None = None,
        k: int | None = None,
    ) -> tuple[LocalizationResult, int]:
        """Hypotheses for one frame and the map version they were computed against."""
        runtime = self.get(map_id)
        camera = intrinsics or runtime.record.camera
        result = localize_frame(
            image_gray,
            camera,
            runtime.vocabulary,
            runtime.index,
            runtime.cache.get,
            config,
            rng,
            prior,
            k,
        )
        return result, runtime.version

"""The server's live memory of its maps: vocabulary, retrieval index and entry cache.

One ``MapRegistry`` per process. A map's runtime is loaded on first use (or at start-up
by ``load_all``): its index comes from the index file when that file is intact and
stamped with the database's map version, and is otherwise rebuilt from the database and
re-saved; it is never served empty.

Every process is a replica: the database's per-map change log (``map_changes``: entry
added, deleted, re-tagged, VLAD rewritten, vocabulary changed, one row per version) is
applied in version order as deltas (:meth:`MapRegistry.catch_up`); only a vocabulary
change (or a gap in the log) rebuilds the whole index. Edits made through this process
catch up right after their commit; edits of other processes (replicas, a CLI
ingestion) are applied by the sync thread (:meth:`MapRegistry.start_sync`: a poll of the
maps' versions every ``sync_interval_s``, woken at once by PostgreSQL's NOTIFY) and by a
version check of at most once per ``version_check_s`` on the query path.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import NotFoundError
from monoloc.core.measurement import MeasurementModel
from monoloc.core.prior import RetrievalPrior
from monoloc.server.index.persist import (
    IndexFileError,
    delete_index,
    load_index,
    rebuild_index,
    save_index,
)
from monoloc.server.index.retrieval import IndexConfig, RetrievalIndex
from monoloc.server.localize import (
    LocalizationResult,
    LocalizeConfig,
    ReferenceEntry,
    localize_frame,
)
from monoloc.server.localize.frame import PRODUCT_STAGES, FrameStages
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage.db import libpq_params, session_scope
from monoloc.server.storage.records import MapChangeRecord, MapRecord
from monoloc.server.vision.features import orb_for_rule
from monoloc.server.vision.vocabulary import Vocabulary

log = logging.getLogger(__name__)

# Float VLADs a map's index may hold in memory (added live, 8 KiB each) before a catch-up
# rewrites its file: 16,384 is 128 MiB.
UNPERSISTED_MAX = 16_384


class ChangeListener:
    """LISTEN on PostgreSQL's change channel: :meth:`wait` returns at the first NOTIFY
    or after ``timeout_s``. Falls back to sleeping when the connection fails."""

    def __init__(self, sqlalchemy_url: str) -> None:
        self._url = sqlalchemy_url
        self._conn = None

    def _connect(self):
        import psycopg

        conn = psycopg.connect(**libpq_params(self._url), autocommit=True)
        conn.execute(f"LISTEN {maps_repo.CHANGES_CHANNEL}")
        return conn

    def wait(self, timeout_s: float) -> None:
        try:
            if self._conn is None:
                self._conn = self._connect()
            for _ in self._conn.notifies(timeout=timeout_s, stop_after=1):
                pass
        except Exception:  # noqa: BLE001 - the sync loop polls anyway
            log.warning("LISTEN connection lost; polling until it is back", exc_info=True)
            self.close()
            time.sleep(timeout_s)

    def close(self) -> None:
        if self._conn is not None:
            try:
                self._conn.close()
            finally:
                self._conn = None


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
        self._stop_sync = threading.Event()
        self._sync_thread: threading.Thread | None = None

    def index_path(self, map_id: int) -> Path:
        return self._index_dir / f"map_{map_id}.index.npz"

    # ---- loading --------------------------------------------------------------------
    def _lookup(self, ids: Sequence[int]) -> list[ReferenceEntry]:
        """The entries that still exist (an entry deleted in the database may linger in
        the index until ``entries_removed`` or the next version check: it is skipped)."""
        with session_scope(self._sessions) as session:
            rows = entries_repo.existing_entry_data(session, list(ids))
        return [ReferenceEntry.from_entry_data(r) for r in rows]

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
                batches = entries_repo.iter_map_vectors(session, map_id)
                index = rebuild_index(path, batches, record.version, self._index_config)
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
        """The map's runtime, loading it on first use (NotFoundError if gone).

        The query path never waits on the database once a map is loaded: while the sync
        thread runs it alone keeps the maps current; without it (embedded use) a query
        checks the version at most once per ``version_check_s``, and only when no other
        thread is checking or applying a change at that moment (it then answers from the
        map as it is, at most one check old). A localize worker that queued on a catch-up
        held its admission place idle for a database round trip, which under CPU
        saturation cost served frames (bench/load.py, two replicas with writes)."""
        with self._lock:
            runtime = self._maps.get(map_id)
        if runtime is None:
            return self.catch_up(map_id)
        if self._sync_thread is not None:
            return runtime
        if time.monotonic() - runtime.checked_at < self._version_check_s:
            return runtime
        lock = self._load_lock(map_id)
        if not lock.acquire(blocking=False):
            return runtime
        try:
            return self._catch_up_locked(map_id)
        finally:
            lock.release()

    def _load_lock(self, map_id: int) -> threading.Lock:
        with self._lock:
            return self._load_locks.setdefault(map_id, threading.Lock())

    def catch_up(self, map_id: int) -> MapRuntime:
        """Bring the map's runtime to the database's version: apply the change log's
        entries above the runtime's version as deltas, or build the runtime (first use, a
        vocabulary change, a gap in the log). NotFoundError if the map is gone."""
        with self._load_lock(map_id):
            return self._catch_up_locked(map_id)

    def _catch_up_locked(self, map_id: int) -> MapRuntime:
        """:meth:`catch_up` with the map's load lock held."""
        with self._lock:
            runtime = self._maps.get(map_id)
        if runtime is None:
            runtime = self._build(map_id)
        else:
            with session_scope(self._sessions) as session:
                record = maps_repo.get_map(session, map_id)
                changes = maps_repo.list_changes(session, map_id, runtime.version)
            if record.version != runtime.version:
                if not self._apply(runtime, changes, record.version):
                    log.info("map %s: rebuilding (vocabulary change or log gap)", map_id)
                    runtime = self._build(map_id)
            runtime.record, runtime.checked_at = record, time.monotonic()
        with self._lock:
            self._maps[map_id] = runtime
        return runtime

    def _apply(self, runtime: MapRuntime, changes: list[MapChangeRecord], version: int) -> bool:
        """Apply ``changes`` (in version order) to ``runtime``; False when they cannot be
        applied as deltas (not contiguous from the runtime's version, or a vocabulary
        change) and the runtime must be rebuilt."""
        expected = list(range(runtime.version + 1, runtime.version + 1 + len(changes)))
        if [c.version for c in changes] != expected or not changes:
            return False
        if any(c.kind == "vocabulary" for c in changes):
            return False
        touched = list(dict.fromkeys(c.entry_id for c in changes if c.entry_id is not None))
        with session_scope(self._sessions) as session:
            vectors = entries_repo.map_vectors_of(session, runtime.record.id, touched)
        present = set(vectors.entry_ids.tolist())
        gone = [i for i in touched if i not in present]
        if gone:
            runtime.index.remove(gone)
        if len(vectors.entry_ids):
            runtime.index.add(vectors.entry_ids, vectors.codes, vectors.vlads, vectors.planar)
        runtime.cache.discard(touched)
        runtime.version = changes[-1].version
        if runtime.index.unpersisted >= UNPERSISTED_MAX:
            # The VLADs added live are held in memory until the index file is rewritten.
            save_index(self.index_path(runtime.record.id), runtime.index, runtime.version)
        self._warm(runtime.cache, vectors.entry_ids, len(runtime.index))
        return runtime.version == version or version < runtime.version

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
    def entries_added(self, map_id: int) -> None:
        """Entries committed by this process: the map catches up from the log now (the
        same path as any replica's), so the next query sees them."""
        self.changed(map_id)

    def entries_removed(self, map_id: int, entry_ids: Sequence[int], new_version: int) -> None:
        self.changed(map_id)

    def entry_retagged(self, map_id: int, entry_id: int) -> None:
        self.changed(map_id)

    def changed(self, map_id: int) -> None:
        """A change was committed to ``map_id``: catch up if the map is in memory."""
        with self._lock:
            loaded = map_id in self._maps
        if loaded:
            try:
                self.catch_up(map_id)
            except NotFoundError:
                self.forget(map_id)

    def version(self, map_id: int) -> int | None:
        """The version of the map in memory (None if not loaded)."""
        with self._lock:
            runtime = self._maps.get(map_id)
        return None if runtime is None else runtime.version

    def sync_once(self) -> int:
        """Catch up every loaded map whose database version differs, forget deleted maps.
        Returns how many maps were caught up."""
        with session_scope(self._sessions) as session:
            versions = maps_repo.map_versions(session)
        with self._lock:
            loaded = {map_id: rt.version for map_id, rt in self._maps.items()}
        n = 0
        for map_id, version in loaded.items():
            if map_id not in versions:
                self.forget(map_id)
            elif versions[map_id] != version:
                try:
                    self.catch_up(map_id)
                    n += 1
                except NotFoundError:
                    self.forget(map_id)
        return n

    def start_sync(self, interval_s: float, listen_url: str | None = None) -> None:
        """Keep the loaded maps current from the database in a daemon thread: every
        ``interval_s``, and at once on a PostgreSQL NOTIFY when ``listen_url`` (a
        ``postgresql`` SQLAlchemy URL) is given."""
        self._stop_sync.clear()
        self._sync_thread = threading.Thread(
            target=self._sync_loop,
            args=(interval_s, listen_url),
            name="monoloc-replica-sync",
            daemon=True,
        )
        self._sync_thread.start()

    def stop_sync(self) -> None:
        self._stop_sync.set()
        if self._sync_thread is not None:
            self._sync_thread.join(10)
            self._sync_thread = None

    def _sync_loop(self, interval_s: float, listen_url: str | None) -> None:
        listener = ChangeListener(listen_url) if listen_url else None
        try:
            while not self._stop_sync.is_set():
                try:
                    self.sync_once()
                except Exception:  # the database may be away for a moment: retry
                    log.exception("replica sync failed; retrying")
                if listener is not None:
                    listener.wait(interval_s)
                else:
                    self._stop_sync.wait(interval_s)
        finally:
            if listener is not None:
                listener.close()

    def forget(self, map_id: int, delete_file: bool = False) -> None:
        """Drop a map from memory (deleted, or its vocabulary changed)."""
        with self._lock:
            self._maps.pop(map_id, None)
        if delete_file:
            delete_index(self.index_path(map_id))

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
        stages: FrameStages = PRODUCT_STAGES,
    ) -> tuple[LocalizationResult, int]:
        """Hypotheses for one frame and the map version they were computed against
        (``stages``: the product's unless a benchmark compares a baseline)."""
        runtime = self.get(map_id)
        camera = intrinsics or runtime.record.camera
        if runtime.record.features:
            # the query described as the map's entries were (maps.features)
            config = replace(config, orb=orb_for_rule(runtime.record.features, config.orb))
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
            stages,
        )
        return result, runtime.version

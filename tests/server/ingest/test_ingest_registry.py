"""The live index of an ingested map (monoloc.server.map_registry.MapRegistry): restart, corrupt and
stale index files, and edits while another thread searches."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import pytest

from monoloc.server.ingest.pipeline import ingest_run
from monoloc.server.ingest.sources import read_kitti_sequence
from monoloc.server.map_registry import MapRegistry
from monoloc.server.vision.binary_code import vlad_binary_code
from monoloc.server.vision.features import extract_features
from monoloc.server.vision.vlad import compute_vlad


@pytest.fixture
def ingested(kitti_root, factory, make_map, make_run, settings):
    """(registry, map id, source) with the hand-made sequence ingested and persisted."""
    seq = read_kitti_sequence(kitti_root.root)
    map_id = make_map()
    registry = MapRegistry(factory, settings.index_dir)
    registry.get(map_id)  # live before the ingestion: fed batch by batch, persisted at the end
    ingest_run(factory, map_id, seq, run_id=make_run(map_id, seq), registry=registry)
    assert registry.index_path(map_id).exists()
    return registry, map_id, seq


def _query(registry, map_id, seq, index=3):
    runtime = registry.get(map_id)
    image = seq.load(seq.frames[index]).image_gray
    vlad = compute_vlad(extract_features(image).descriptors, runtime.vocabulary)
    return runtime.index.search(vlad, vlad_binary_code(vlad), k=5)


def test_entries_added_live_are_cached_before_the_first_query(
    kitti_root, factory, make_map, make_run, settings
):
    seq = read_kitti_sequence(kitti_root.root)
    map_id = make_map()
    registry = MapRegistry(factory, settings.index_dir, version_check_s=1e9)
    runtime = registry.get(map_id)
    assert len(runtime.cache) == 0
    ingest_run(factory, map_id, seq, run_id=make_run(map_id, seq), registry=registry)
    assert registry.get(map_id) is runtime  # fed live, not rebuilt (which warms anyway)
    ids = runtime.index.entry_ids().tolist()
    assert ids and all(i in runtime.cache for i in ids)
    assert len(runtime.cache) == len(ids)


def test_index_survives_a_restart(ingested, factory, settings, caplog):
    registry, map_id, seq = ingested
    before = _query(registry, map_id, seq)
    caplog.clear()
    caplog.set_level(logging.INFO, logger="monoloc.server.map_registry")
    restarted = MapRegistry(factory, settings.index_dir)
    after = _query(restarted, map_id, seq)
    assert "index loaded from" in caplog.text and "rebuilding" not in caplog.text
    np.testing.assert_array_equal(after.entry_ids, before.entry_ids)
    np.testing.assert_allclose(after.distances, before.distances, atol=1e-6)


def test_corrupt_index_file_is_rebuilt(ingested, factory, settings, caplog):
    registry, map_id, seq = ingested
    before = _query(registry, map_id, seq)
    path = registry.index_path(map_id)
    data = bytearray(path.read_bytes())
    data[len(data) // 2 : len(data) // 2 + 64] = b"\x00" * 64
    path.write_bytes(bytes(data))
    caplog.clear()
    caplog.set_level(logging.INFO, logger="monoloc.server.map_registry")
    restarted = MapRegistry(factory, settings.index_dir)
    after = _query(restarted, map_id, seq)
    assert "rebuilding from the database" in caplog.text
    assert len(restarted.get(map_id).index) == 8
    np.testing.assert_array_equal(after.entry_ids, before.entry_ids)
    caplog.clear()
    MapRegistry(factory, settings.index_dir).get(map_id)  # the rebuilt file is good again
    assert "rebuilding" not in caplog.text


def test_stale_index_file_is_rebuilt(ingested, factory, settings, caplog):
    from monoloc.server.storage import entries as entries_repo
    from monoloc.server.storage.db import session_scope

    registry, map_id, seq = ingested
    with session_scope(factory) as session:  # an edit the index file does not know about
        first = entries_repo.list_entries(session, map_id, limit=1)[0]
        entries_repo.delete_entry(session, first.id)
    caplog.clear()
    caplog.set_level(logging.INFO, logger="monoloc.server.map_registry")
    restarted = MapRegistry(factory, settings.index_dir)
    assert len(restarted.get(map_id).index) == 7
    assert "is stale: map version 8, database 9" in caplog.text


def test_add_and_remove_while_searching_from_another_thread(ingested, factory, kitti_root):
    from monoloc.server.ingest.single import add_single_image
    from monoloc.server.localize import LocalizeConfig
    from monoloc.server.storage import entries as entries_repo
    from monoloc.server.storage.db import session_scope

    registry, map_id, seq = ingested
    query = seq.load(seq.frames[4]).image_gray
    stop, errors, searches = threading.Event(), [], []

    def search_loop():
        rng = np.random.default_rng(0)
        try:
            while not stop.is_set():
                result, _ = registry.localize(map_id, query, LocalizeConfig(k=5), rng)
                searches.append(len(result.retrieved_ids))
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    thread = threading.Thread(target=search_loop)
    thread.start()
    try:
        added = []
        for i, frame in enumerate(seq.frames[:4]):
            loaded = seq.load(frame)
            # A shifted copy of the image: another source file, so another entry.
            shifted = np.roll(loaded.image_gray, 3 + i, axis=1)
            import cv2

            ok, png = cv2.imencode(".png", shifted)
            summary, created = add_single_image(
                factory,
                map_id,
                png.tobytes(),
                frame.T_world_from_cam,
                loaded.source,
                registry=registry,
                intrinsics=seq.intrinsics,
            )
            assert created
            added.append(summary.id)
        for entry_id in added[:2]:
            with session_scope(factory) as session:
                version = entries_repo.delete_entry(session, entry_id)
            registry.entries_removed(map_id, [entry_id], version)
    finally:
        stop.set()
        thread.join(timeout=30)
    assert not errors and len(searches) > 0
    runtime = registry.get(map_id)
    with session_scope(factory) as session:
        in_db = {e.id for e in entries_repo.list_entries(session, map_id, limit=100)}
    assert set(runtime.index.entry_ids().tolist()) == in_db and len(in_db) == 10


def test_entry_deleted_under_a_search_is_skipped_not_an_error(ingested, factory):
    """An entry deleted in the database but still in the live index (the instant between
    the delete's commit and ``entries_removed``, or a delete by another process before
    the version check) is dropped from the candidates instead of failing the query."""
    from monoloc.server.localize import LocalizeConfig
    from monoloc.server.storage import entries as entries_repo
    from monoloc.server.storage.db import session_scope

    registry, map_id, seq = ingested
    query = seq.load(seq.frames[4]).image_gray
    runtime = registry.get(map_id)
    runtime.checked_at += 3600.0  # no version check for the next hour
    first, _ = registry.localize(map_id, query, LocalizeConfig(k=8), np.random.default_rng(0))
    victim = int(first.retrieved_ids[0])
    runtime.cache.discard([victim])
    with session_scope(factory) as session:
        entries_repo.delete_entry(session, victim)
    result, _ = registry.localize(map_id, query, LocalizeConfig(k=8), np.random.default_rng(0))
    assert victim in result.retrieved_ids.tolist()  # the index has not heard of it yet
    assert victim not in [h.entry_id for h in result.hypotheses]
    assert len(result.hypotheses) >= 1


def test_a_query_does_not_wait_for_a_catch_up_in_progress(ingested):
    """A query whose version check is due while another thread is catching the map up
    (holding the map's load lock through database queries) answers from the map as it
    is instead of queueing behind the catch-up; it checks again next time."""
    registry, map_id, _ = ingested
    registry._version_check_s = 0.0  # every query's check is due
    runtime = registry.get(map_id)
    got = []
    with registry._load_lock(map_id):  # a catch-up in progress
        thread = threading.Thread(target=lambda: got.append(registry.get(map_id)))
        thread.start()
        thread.join(timeout=30)  # a bound: blocked, it would wait for the lock's release
        blocked = thread.is_alive()
    thread.join(timeout=30)
    assert not blocked
    assert got == [runtime]


def test_queries_read_no_database_while_the_sync_thread_keeps_the_map_current(ingested, factory):
    """With the sync thread running, the query path leaves the version checks to it:
    no database session per query, and a delete by another process still reaches the
    index within the sync interval."""
    from monoloc.server.storage import entries as entries_repo
    from monoloc.server.storage.db import session_scope

    registry, map_id, _ = ingested
    sessions_opened = []

    def counting_factory():
        sessions_opened.append(threading.current_thread().name)
        return factory()

    registry._sessions = counting_factory
    registry._version_check_s = 0.0
    registry.start_sync(0.05)
    try:
        victim = int(registry.get(map_id).index.entry_ids()[0])
        for _ in range(50):
            registry.get(map_id)
        assert [name for name in sessions_opened if name != "monoloc-replica-sync"] == []
        with session_scope(factory) as session:  # another process's delete
            entries_repo.delete_entry(session, victim)
        deadline = time.monotonic() + 30.0  # a bound for a loaded machine
        while victim in registry.get(map_id).index and time.monotonic() < deadline:
            time.sleep(0.02)
        assert victim not in registry.get(map_id).index
    finally:
        registry.stop_sync()

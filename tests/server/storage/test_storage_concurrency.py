import threading

import numpy as np
import pytest

from monoloc.core.camera import KITTI_CAM0
from monoloc.server.settings import Settings
from monoloc.server.storage.db import create_engine_for, make_session_factory, session_scope
from monoloc.server.storage.entries import add_entry, count_entries, list_entries
from monoloc.server.storage.maps import create_map, get_map, get_or_create_vocabulary
from monoloc.server.storage.migrate import upgrade_database


def _run_threads(targets):
    errors: list[BaseException] = []
    barrier = threading.Barrier(len(targets))

    def wrap(fn):
        def run():
            barrier.wait()
            try:
                fn()
            except BaseException as exc:  # surfaced in the main thread below
                errors.append(exc)

        return run

    threads = [threading.Thread(target=wrap(fn)) for fn in targets]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert not any(t.is_alive() for t in threads)
    return errors


def test_concurrent_writers_wait_instead_of_failing(factory, map_id, make_entry):
    n_per_writer = 40
    entries = {w: [make_entry(f"{w}-{i}", x_m=float(i)) for i in range(n_per_writer)] for w in "ab"}

    def writer(name):
        def run():
            for new in entries[name]:
                with session_scope(factory) as session:
                    get_map(session, map_id)  # read first, then write: the risky pattern
                    add_entry(session, map_id, new)

        return run

    def reader():
        for _ in range(60):
            with session_scope(factory) as session:
                list_entries(session, map_id, limit=10)

    errors = _run_threads([writer("a"), writer("b"), reader])
    assert errors == []
    with session_scope(factory) as session:
        assert count_entries(session, map_id) == 2 * n_per_writer
        assert get_map(session, map_id).version == 2 * n_per_writer


def test_racing_duplicate_ingestions_add_each_image_once(factory, map_id, make_entry):
    news = [make_entry(f"same-{i}") for i in range(30)]
    created: list[bool] = []

    def ingest():
        for new in news:
            with session_scope(factory) as session:
                created.append(add_entry(session, map_id, new)[1])

    errors = _run_threads([ingest, ingest])
    assert errors == []
    assert sum(created) == len(news) and len(created) == 2 * len(news)
    with session_scope(factory) as session:
        assert count_entries(session, map_id) == len(news)
        assert get_map(session, map_id).version == len(news)


@pytest.mark.parametrize(("busy_timeout_ms", "should_wait"), [(0, False), (5000, True)])
def test_busy_timeout_makes_a_writer_wait_for_the_lock(
    tmp_path, make_entry, busy_timeout_ms, should_wait
):
    from sqlalchemy.exc import OperationalError

    settings = Settings(data_dir=tmp_path, busy_timeout_ms=busy_timeout_ms)
    upgrade_database(settings.database_url)
    engine = create_engine_for(settings)
    factory = make_session_factory(engine)
    with session_scope(factory) as session:
        vocab, _ = get_or_create_vocabulary(session, np.zeros((64, 32), np.float32))
        map_id = create_map(session, "m", KITTI_CAM0, vocab.id).id
    holder = engine.raw_connection()
    holder.execute("BEGIN IMMEDIATE")  # another writer holds the lock for 0.3 s
    release = threading.Timer(0.3, holder.rollback)
    release.start()
    try:
        if should_wait:
            with session_scope(factory) as session:
                assert add_entry(session, map_id, make_entry("a"))[1]
        else:
            with pytest.raises(OperationalError, match="database is locked"):
                with session_scope(factory) as session:
                    add_entry(session, map_id, make_entry("a"))
    finally:
        release.join()
        holder.close()
        engine.dispose()


@pytest.fixture(params=["sqlite", "postgresql"])
def calibration_map(request, tmp_path):
    """(session factory, map id) on a SQLite file or a fresh PostgreSQL database."""
    if request.param == "sqlite":
        url = f"sqlite:///{tmp_path / 'db' / 'monoloc.db'}"
    else:
        url = request.getfixturevalue("postgres_url")
    settings = Settings(data_dir=tmp_path / "data", database_url=url)
    upgrade_database(settings.database_url)
    engine = create_engine_for(settings)
    factory = make_session_factory(engine)
    centres = np.random.default_rng(1).uniform(0, 255, (64, 32)).astype(np.float32)
    with session_scope(factory) as session:
        vocab, _ = get_or_create_vocabulary(session, centres, "test vocabulary")
        map_id = create_map(session, "m", KITTI_CAM0, vocab.id).id
    yield factory, map_id
    engine.dispose()


def test_calibration_read_modify_writes_lose_nothing(calibration_map):
    """Writers that each add one condition to the stored calibration at once (a base and a
    condition calibration finishing together) all land: the read happens under the map's
    write lock, not on a snapshot another writer is about to replace."""
    import time

    from monoloc.core.measurement import MeasurementModel
    from monoloc.server.storage.maps import update_calibration

    factory, map_id = calibration_map
    with session_scope(factory) as session:
        base = {**MeasurementModel().to_dict(), "conditions": {}}
        update_calibration(session, map_id, lambda stored: base)

    def writer(name: str):
        def run():
            def change(stored):
                time.sleep(0.05)  # widen the window between the read and the write
                night = {**base, "conditions": {}}
                return {**stored, "conditions": {**stored["conditions"], name: night}}

            with session_scope(factory) as session:
                update_calibration(session, map_id, change)

        return run

    names = [f"c{i}" for i in range(6)]
    assert _run_threads([writer(n) for n in names]) == []
    with session_scope(factory) as session:
        stored = get_map(session, map_id).calibration
    assert sorted(stored["conditions"]) == names and stored["Sigma1"] == base["Sigma1"]

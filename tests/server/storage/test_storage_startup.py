"""Processes starting together on one database: the start-up lock, the schema upgrade and
the bootstrap key (replicas used to race and the loser exited on a duplicate key)."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import pytest
from sqlalchemy import event, func, select

from monoloc.server.api.bootstrap import bootstrap_admin_key, prepare_database
from monoloc.server.settings import Settings
from monoloc.server.storage.db import (
    StartupLockTimeoutError,
    create_engine_for,
    make_session_factory,
    session_scope,
    startup_lock,
)
from monoloc.server.storage.migrate import current_revision, head_revision
from monoloc.server.storage.models import ApiKey

ADMIN_KEY = "mlk_" + "s" * 40


@pytest.fixture(params=["sqlite", "postgresql"])
def any_database_url(request, tmp_path) -> str:
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'db' / 'monoloc.db'}"
    return request.getfixturevalue("postgres_url")


def _settings(tmp_path, url: str) -> Settings:
    return Settings(data_dir=tmp_path / "data", database_url=url, bootstrap_admin_key=ADMIN_KEY)


def test_the_startup_lock_keeps_a_second_holder_out_until_released(any_database_url):
    entered = threading.Event()

    def second_holder() -> None:
        with startup_lock(any_database_url):
            entered.set()

    with startup_lock(any_database_url):
        thread = threading.Thread(target=second_holder)
        thread.start()
        assert not entered.wait(0.5), "a second process entered while the lock was held"
    assert entered.wait(10.0), "the second process never got the lock after release"
    thread.join()


def test_a_lock_held_too_long_is_a_clear_error(any_database_url):
    with startup_lock(any_database_url):
        outcome: list[BaseException] = []

        def impatient() -> None:
            try:
                with startup_lock(any_database_url, timeout_s=0.2):
                    pass
            except BaseException as exc:  # noqa: BLE001 - handed to the main thread
                outcome.append(exc)

        thread = threading.Thread(target=impatient)
        thread.start()
        thread.join()
    assert len(outcome) == 1 and isinstance(outcome[0], StartupLockTimeoutError)
    assert "start-up lock" in str(outcome[0])


def test_replicas_starting_together_all_come_up_with_one_key(tmp_path, any_database_url):
    settings = _settings(tmp_path, any_database_url)
    n_replicas = 4
    barrier = threading.Barrier(n_replicas)

    def start_one(_: int):
        barrier.wait()
        return prepare_database(settings)

    with ThreadPoolExecutor(n_replicas) as pool:
        engines = list(pool.map(start_one, range(n_replicas)))  # raises what a replica raised
    assert current_revision(any_database_url) == head_revision()
    with session_scope(make_session_factory(engines[0])) as session:
        names = session.scalars(select(ApiKey.name)).all()
    assert names == ["bootstrap"]
    for engine in engines:
        engine.dispose()


def test_a_key_stored_by_another_process_mid_bootstrap_is_not_an_error(tmp_path):
    """Without the lock (a caller that does not take it), another process may insert the
    key between this one's count and its insert: the unique hash refuses the second copy
    and bootstrap reports that it stored nothing."""
    settings = _settings(tmp_path, f"sqlite:///{tmp_path / 'monoloc.db'}")
    engine = prepare_database(settings.model_copy(update={"bootstrap_admin_key": None}))
    sessions = make_session_factory(engine)
    assert not _count_keys(sessions)
    other_process = make_session_factory(create_engine_for(settings))
    raced: list[bool] = []

    @event.listens_for(engine, "after_cursor_execute")
    def _insert_after_our_count(_conn, _cursor, statement: str, *_args) -> None:
        if not raced and "count(" in statement.lower():
            raced.append(bootstrap_admin_key(other_process, settings))

    assert bootstrap_admin_key(sessions, settings) is False
    assert raced == [True]
    assert _count_keys(other_process) == 1
    engine.dispose()


def _count_keys(sessions) -> int:
    with session_scope(sessions) as session:
        return int(session.scalar(select(func.count(ApiKey.id))))

"""Revision 0009 (the cameras table) on a real SQLite file and a real PostgreSQL
database (tests/pg_cluster.py): upgraded onto a database of
revision 0008 whose keys stay as they were, cameras stored with their lens and read
back, a camera's key row gone leaves the camera (key_id NULL), and a downgrade drops the
table with the keys intact."""

from __future__ import annotations

import pytest
from sqlalchemy import inspect

from monoloc.core.camera import CameraIntrinsics, LensDistortion
from monoloc.core.errors import NotFoundError
from monoloc.server.storage import cameras as cameras_repo
from monoloc.server.storage.migrate import alembic_config, current_revision, upgrade_database


def test_revision_0009_adds_cameras_and_goes_back(tmp_path):
    _upgrade_store_downgrade(f"sqlite:///{tmp_path / 'c.db'}")


def test_revision_0009_on_postgresql(postgres_url):
    _upgrade_store_downgrade(postgres_url)


def _upgrade_store_downgrade(url: str) -> None:
    from alembic import command

    from monoloc.server.storage.db import (
        create_engine_for_url,
        make_session_factory,
        session_scope,
    )
    from monoloc.server.storage.keys import create_api_key, list_api_keys

    command.upgrade(alembic_config(url), "0008")
    engine = create_engine_for_url(url)  # the server's pragmas: foreign keys enforced
    with engine.connect() as conn:
        assert "cameras" not in inspect(conn).get_table_names()
    factory = make_session_factory(engine)
    with session_scope(factory) as session:
        create_api_key(session, "car1", ["localize"])
    upgrade_database(url)
    assert current_revision(url) == "0010"
    lens = LensDistortion("plumb_bob", (-0.28, 0.09, 0.0006, -0.0004))
    camera = CameraIntrinsics(640.0, 640.0, 511.5, 287.5, 1024, 576, lens)
    with session_scope(factory) as session:
        (key,) = list_api_keys(session)
        fleet = cameras_repo.create_camera(session, "  fleet-front ", camera, key.id)
        pinhole = cameras_repo.create_camera(session, "pinhole", camera.pinhole, None)
    with session_scope(factory) as session:
        got = cameras_repo.get_camera(session, fleet.id)
        assert got.intrinsics == camera and got.name == "fleet-front" and got.key_id == key.id
        assert cameras_repo.get_camera(session, pinhole.id).intrinsics.distortion is None
        assert [c.id for c in cameras_repo.list_cameras(session)] == [fleet.id, pinhole.id]
        with pytest.raises(NotFoundError, match="camera 99 does not exist"):
            cameras_repo.get_camera(session, 99)
    with engine.begin() as conn:  # the registering key's row goes: the camera stays
        conn.exec_driver_sql("DELETE FROM api_keys")
    with session_scope(factory) as session:
        assert cameras_repo.get_camera(session, fleet.id).key_id is None
        create_api_key(session, "car2", ["localize"])
    command.downgrade(alembic_config(url), "0008")
    with engine.connect() as conn:
        assert "cameras" not in inspect(conn).get_table_names()
        names = [r[0] for r in conn.exec_driver_sql("SELECT name FROM api_keys")]
    assert names == ["car2"]
    engine.dispose()

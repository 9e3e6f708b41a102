"""A replica's LISTEN connection (ChangeListener) on a multi-host URL, as a shard group on
a pg_auto_failover formation gives its replicas (host=a&host=b&target_session_attrs=
read-write): it skips the node it cannot reach, listens on the one it can, and a NOTIFY
wakes it at once (before the fix it connected to libpq's default socket instead and the
replica fell back to polling); the console's relay connection likewise."""

from __future__ import annotations

import threading
import time

from sqlalchemy import create_engine, text
from sqlalchemy.engine import make_url

from monoloc.server.api.console.relay import _connect as relay_connect
from monoloc.server.map_registry import ChangeListener
from monoloc.server.storage.maps import CHANGES_CHANNEL


def test_listen_on_a_multi_host_url_wakes_at_the_first_notify(postgres_admin_url, tmp_path):
    url = make_url(postgres_admin_url)
    socket_dir, port = url.query["host"], url.query["port"]
    dead = tmp_path / "nobody"  # a socket directory no server listens in
    hosts = f"host={dead}:{port}&host={socket_dir}:{port}&target_session_attrs=read-write"
    multi = f"postgresql+psycopg://{url.username}@/{url.database}?{hosts}"
    listener = ChangeListener(multi)
    engine = create_engine(postgres_admin_url, isolation_level="AUTOCOMMIT")
    try:
        listener.wait(0.01)  # connects and LISTENs
        assert listener._conn is not None, "the listener did not connect"

        def notify() -> None:
            time.sleep(0.5)
            with engine.connect() as connection:
                connection.execute(text(f"NOTIFY {CHANGES_CHANNEL}, '1:2'"))

        threading.Thread(target=notify).start()
        started = time.monotonic()
        listener.wait(30.0)
        waited = time.monotonic() - started
        assert listener._conn is not None
        assert 0.4 < waited < 10.0, waited  # woken by the NOTIFY, not the 30 s timeout
        # the console's live-vehicle relay listens the same way
        relayed = relay_connect(multi)
        try:
            assert relayed.execute(text("SELECT 1").text).fetchone() == (1,)
        finally:
            relayed.close()
    finally:
        listener.close()
        engine.dispose()

"""The live-vehicle board shared by the replicas through PostgreSQL's LISTEN/NOTIFY.

Behind a load balancer a vehicle streams to one replica and the console's page asks
another: each replica sends its vehicles' public state (``VehicleBoard.outgoing``: on a
change, at most every ``period_s``, and every ``heartbeat_s`` while connected) on
:data:`CHANNEL`, listens on it, and merges what the others send into its board. A
notification carries one vehicle (its JSON, under PostgreSQL's 8000-byte payload limit:
hypotheses are cut to fit). Nothing of it is stored; with SQLite (one machine, one
process unless ``--workers``) there is no relay.
"""

from __future__ import annotations

import json
import logging
import threading
from typing import Any

from monoloc.server.api.console.live import VehicleBoard
from monoloc.server.storage.db import libpq_params

log = logging.getLogger(__name__)

CHANNEL = "monoloc_live_vehicles"
MAX_PAYLOAD_BYTES = 7900  # PostgreSQL refuses a NOTIFY payload of 8000 bytes or more


def encode(replica_id: str, map_id: int, public: dict[str, Any]) -> str | None:
    """One notification's payload; hypotheses dropped from the end until it fits (None
    if even without them it does not)."""
    public = dict(public)
    hypotheses = list(public.get("hypotheses") or [])
    while True:
        public["hypotheses"] = hypotheses
        payload = json.dumps({"r": replica_id, "m": map_id, "v": public}, separators=(",", ":"))
        if len(payload.encode()) <= MAX_PAYLOAD_BYTES:
            return payload
        if not hypotheses:
            return None
        hypotheses = hypotheses[: len(hypotheses) // 2]


def decode_into(board: VehicleBoard, payload: str) -> None:
    try:
        message = json.loads(payload)
        board.merge(str(message["r"]), int(message["m"]), message["v"])
    except (ValueError, KeyError, TypeError):
        log.warning("ignored a malformed live-vehicle notification")


def _connect(sqlalchemy_url: str):
    import psycopg

    return psycopg.connect(**libpq_params(sqlalchemy_url), autocommit=True)


class BoardRelay:
    """A thread sending this replica's vehicles and merging the others' (see module)."""

    def __init__(
        self,
        board: VehicleBoard,
        database_url: str,
        period_s: float = 0.25,
        heartbeat_s: float = 2.0,
    ) -> None:
        self.board, self.database_url = board, database_url
        self.period_s, self.heartbeat_s = period_s, heartbeat_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="live-vehicles", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)

    def _run(self) -> None:
        conn = None
        while not self._stop.is_set():
            try:
                if conn is None:
                    conn = _connect(self.database_url)
                    # every notification, also those arriving while a NOTIFY is sent
                    conn.add_notify_handler(lambda n: decode_into(self.board, n.payload))
                    conn.execute(f"LISTEN {CHANNEL}")
                for map_id, public in self.board.outgoing(self.heartbeat_s):
                    payload = encode(self.board.replica_id, map_id, public)
                    if payload is not None:
                        conn.execute("SELECT pg_notify(%s, %s)", (CHANNEL, payload))
                for note in conn.notifies(timeout=self.period_s, stop_after=64):
                    decode_into(self.board, note.payload)  # a second merge changes nothing
            except Exception:  # noqa: BLE001 - the board stays local until it is back
                log.warning("live-vehicle relay lost its connection; retrying", exc_info=True)
                if conn is not None:
                    try:
                        conn.close()
                    except Exception:  # noqa: BLE001
                        pass
                conn = None
                self._stop.wait(1.0)
        if conn is not None:
            conn.close()

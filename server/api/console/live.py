"""What the console's live page shows of each vehicle streaming to a map.

The stream route opens one :class:`VehicleFeed` per WebSocket and reports every answered
frame to it; the board keeps, per vehicle, its latest estimate and hypotheses, its frame
rate and its latency, and a version number that changes with every report (the live
page's event stream sends a snapshot when it changes).

The server does not run the vehicle's filter: the *estimate* is the retrieval prior the
vehicle sent with the frame (the client builds it from its filter's estimate, see
client/tracking.py), else the best hypothesis (most inliers) of the answer. Latency is
the server's time from a frame's arrival to its answer being sent (queueing included).
Poses are planar, in the z-up world (metres, radians).

Replicas share their boards (server/api/console/relay.py): each vehicle's public state is
sent to the other replicas when it changes (and every few seconds while connected), and
a board shows the vehicles other replicas reported next to its own; every vehicle names
its ``replica``. A vehicle whose replica stopped reporting is shown disconnected, then
forgotten like a closed one.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class PlanarEstimate:
    x_m: float
    y_m: float
    yaw_rad: float | None

    def to_json(self) -> dict[str, Any]:
        return {"x_m": self.x_m, "y_m": self.y_m, "yaw_rad": self.yaw_rad}


@dataclass(frozen=True)
class BoardConfig:
    """rate_window_s: frame rate and latency over the last seconds; forget_after_s: a
    disconnected vehicle stays on the board this long; max_hypotheses: kept per frame."""

    rate_window_s: float = 5.0
    forget_after_s: float = 60.0
    max_hypotheses: int = 10
    stale_after_s: float = 6.0  # another replica's vehicle without a report: disconnected


@dataclass
class _Vehicle:
    vehicle_id: int
    map_id: int
    name: str
    connected_at_s: float
    connected: bool = True
    frames: int = 0
    dropped: int = 0
    errors: int = 0
    last_seq: int | None = None
    last_t_s: float | None = None
    last_frame_s: float | None = None
    estimate: PlanarEstimate | None = None
    estimate_source: str | None = None
    hypotheses: list[dict[str, Any]] = field(default_factory=list)
    recent: deque[tuple[float, float]] = field(default_factory=deque)  # (arrival, latency)
    closed_at_s: float | None = None
    revision: int = 0


@dataclass
class _Remote:
    """A vehicle of another replica: its public state as sent, when it arrived here."""

    map_id: int
    public: dict[str, Any]
    received_s: float


class VehicleBoard:
    """Thread-safe per-vehicle state of the streams (one board per app)."""

    def __init__(
        self, config: BoardConfig = BoardConfig(), clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.config, self.clock = config, clock
        self._lock = threading.Lock()
        self._vehicles: dict[int, _Vehicle] = {}
        self._next_id = 1
        self.version = 0
        self.replica_id = uuid.uuid4().hex[:12]
        self._remote: dict[tuple[str, int], _Remote] = {}
        self._sent: dict[int, tuple[int, float]] = {}  # vehicle -> (revision, sent at)

    def connect(self, map_id: int, name: str) -> VehicleFeed:
        """A feed for a new stream on ``map_id`` by the key named ``name``."""
        with self._lock:
            vehicle = _Vehicle(self._next_id, map_id, name, self.clock())
            self._vehicles[vehicle.vehicle_id] = vehicle
            self._next_id += 1
            self.version += 1
        return VehicleFeed(self, vehicle.vehicle_id)

    def _update(self, vehicle_id: int, change: Callable[[_Vehicle, float], None]) -> None:
        with self._lock:
            vehicle = self._vehicles.get(vehicle_id)
            if vehicle is not None:
                change(vehicle, self.clock())
                vehicle.revision += 1
                self.version += 1

    def snapshot(self, map_id: int) -> dict[str, Any]:
        """``{"version", "vehicles": [...]}`` for the vehicles of ``map_id`` on every
        replica: this one's, oldest first, then the others' as last reported."""
        now = self.clock()
        with self._lock:
            self._forget(now)
            vehicles = [self._public(v, now) for v in self._vehicles.values() if v.map_id == map_id]
            vehicles += [
                self._remote_public(r, now) for r in self._remote.values() if r.map_id == map_id
            ]
            return {"version": self.version, "vehicles": vehicles}

    def outgoing(self, heartbeat_s: float) -> list[tuple[int, dict[str, Any]]]:
        """(map id, public state) of this replica's vehicles changed since last asked, or
        connected and not sent for ``heartbeat_s``: what to tell the other replicas."""
        now = self.clock()
        out = []
        with self._lock:
            for i, v in self._vehicles.items():
                revision, sent_s = self._sent.get(i, (-1, -float("inf")))
                if v.revision != revision or (v.connected and now - sent_s >= heartbeat_s):
                    out.append((v.map_id, self._public(v, now)))
                    self._sent[i] = (v.revision, now)
            for i in [i for i in self._sent if i not in self._vehicles]:
                del self._sent[i]
        return out

    def merge(self, replica_id: str, map_id: int, public: dict[str, Any]) -> None:
        """A vehicle's state reported by replica ``replica_id`` (this one's are ignored)."""
        if replica_id == self.replica_id:
            return
        with self._lock:
            key = (replica_id, int(public["vehicle_id"]))
            self._remote[key] = _Remote(int(map_id), dict(public), self.clock())
            self.version += 1

    def _remote_public(self, r: _Remote, now: float) -> dict[str, Any]:
        age_s = now - r.received_s
        public = dict(r.public)
        if public.get("connected") and age_s > self.config.stale_after_s:
            public["connected"] = False  # its replica stopped reporting it
        if public.get("connected"):
            public["connected_for_s"] = round(public["connected_for_s"] + age_s, 3)
            if public.get("since_last_frame_s") is not None:
                public["since_last_frame_s"] = round(public["since_last_frame_s"] + age_s, 3)
        return public

    def _forget(self, now: float) -> None:
        stale = [
            i
            for i, v in self._vehicles.items()
            if v.closed_at_s is not None and now - v.closed_at_s > self.config.forget_after_s
        ]
        for i in stale:
            del self._vehicles[i]
        # another replica's vehicle: forgotten as long after its last report
        gone = [
            k for k, r in self._remote.items() if now - r.received_s > self.config.forget_after_s
        ]
        for k in gone:
            del self._remote[k]

    def _public(self, v: _Vehicle, now: float) -> dict[str, Any]:
        window = [(a, lat) for a, lat in v.recent if now - a <= self.config.rate_window_s]
        if len(window) >= 2 and window[-1][0] > window[0][0]:
            rate_hz = (len(window) - 1) / (window[-1][0] - window[0][0])
        else:
            rate_hz = 0.0
        latencies = sorted(lat for _, lat in window)
        idle_s = None if v.last_frame_s is None else round(now - v.last_frame_s, 3)
        return {
            "vehicle_id": v.vehicle_id,
            "replica": self.replica_id,
            "name": v.name,
            "connected": v.connected,
            "connected_for_s": round(now - v.connected_at_s, 3),
            "frames": v.frames,
            "dropped": v.dropped,
            "errors": v.errors,
            "last_seq": v.last_seq,
            "last_t_s": v.last_t_s,
            "since_last_frame_s": idle_s,
            "frame_rate_hz": round(rate_hz, 2),
            "latency_ms_p50": _percentile_ms(latencies, 0.5),
            "latency_ms_max": _percentile_ms(latencies, 1.0),
            "estimate": v.estimate.to_json() if v.estimate else None,
            "estimate_source": v.estimate_source,
            "hypotheses": v.hypotheses,
        }


def _percentile_ms(sorted_s: Sequence[float], q: float) -> float | None:
    if not sorted_s:
        return None
    return round(1e3 * sorted_s[min(len(sorted_s) - 1, int(q * (len(sorted_s) - 1) + 0.5))], 2)


class VehicleFeed:
    """One stream's reports to the board."""

    def __init__(self, board: VehicleBoard, vehicle_id: int) -> None:
        self.board, self.vehicle_id = board, vehicle_id

    def answered(
        self,
        seq: int | None,
        t_s: float | None,
        received_s: float,
        prior: PlanarEstimate | None,
        hypotheses: Sequence[dict[str, Any]],
    ) -> None:
        """A localized frame: ``hypotheses`` as the answer's JSON (``pose``, ``n_inliers``
        ...), best first; ``received_s`` the frame's arrival on the board's clock."""
        kept = [
            {"entry_id": h["entry_id"], "n_inliers": h["n_inliers"], **h["pose"]}
            for h in hypotheses[: self.board.config.max_hypotheses]
        ]

        def change(v: _Vehicle, now: float) -> None:
            v.frames += 1
            v.last_seq, v.last_t_s, v.last_frame_s = seq, t_s, now
            v.hypotheses = kept
            if prior is not None:
                v.estimate, v.estimate_source = prior, "vehicle prior"
            elif kept:
                best = kept[0]
                v.estimate = PlanarEstimate(best["x_m"], best["y_m"], best["yaw_rad"])
                v.estimate_source = "best hypothesis"
            v.recent.append((received_s, now - received_s))
            while v.recent and now - v.recent[0][0] > self.board.config.rate_window_s:
                v.recent.popleft()

        self.board._update(self.vehicle_id, change)

    def report(self, body: dict[str, Any], received_s: float, prior: Any = None) -> None:
        """One stream answer as sent (its JSON ``body``); ``prior``: the frame's
        RetrievalPrior (or anything with x_m, y_m, yaw_rad), None without one."""
        if body.get("dropped"):
            self.skipped(dropped=True)
        elif "error" in body:
            self.skipped(dropped=False)
        else:
            estimate = (
                PlanarEstimate(float(prior.x_m), float(prior.y_m), prior.yaw_rad)
                if prior is not None
                else None
            )
            self.answered(body.get("seq"), body.get("t"), received_s, estimate, body["hypotheses"])

    def skipped(self, *, dropped: bool) -> None:
        """A frame dropped unprocessed (``dropped``) or answered with an error."""

        def change(v: _Vehicle, now: float) -> None:
            if dropped:
                v.dropped += 1
            else:
                v.errors += 1

        self.board._update(self.vehicle_id, change)

    def close(self) -> None:
        def change(v: _Vehicle, now: float) -> None:
            v.connected, v.closed_at_s = False, now

        self.board._update(self.vehicle_id, change)


def vehicle_board(app: Any) -> VehicleBoard:
    """The app's board (``app.state.vehicle_board``), made on first use."""
    board = getattr(app.state, "vehicle_board", None)
    if board is None:
        board = app.state.vehicle_board = VehicleBoard()
    return board

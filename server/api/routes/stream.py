"""``WS /v1/maps/{map_id}/stream``: one WebSocket per vehicle (localize scope).

Key: header ``X-API-Key`` / ``Authorization: Bearer``, or ``?key=`` (browsers cannot set
WebSocket headers). Refusals happen before the handshake completes, as HTTP answers:
401/403 (key), 404 (map).

In: binary messages, each = 4-byte big-endian header length + UTF-8 JSON header +
encoded image (PNG/JPEG). Header: ``{"seq": int, "t": float, "prior": {"x_m", "y_m",
"radius_m", "yaw_rad"?, "yaw_tolerance_rad"?}?, "k": int?, "seed": int?,
"intrinsics": {"fx", "fy", "cx", "cy"}?}``.

Out: one JSON text message per frame, in the order the frames arrived: the localize
answer plus ``seq`` and ``t``; or ``{"seq", "t", "dropped": true, "reason": "stale"}``;
or ``{"seq", "error": {"code", "message"}}`` for a frame that could not be processed
(a header without a readable ``seq`` gets ``"seq": null``).

Back-pressure: at most ``stream_max_pending_frames`` frames wait for processing. When
another arrives, the oldest waiting frame is dropped (its image freed at once) and
answered as dropped when its turn comes, so answers keep arrival order. A client owed
more than ``max_stream_backlog`` answers is closed with code 1008.
"""

from __future__ import annotations

import json
import logging
import struct
from collections import deque
from dataclasses import dataclass
from typing import Any

import anyio
from fastapi import APIRouter, WebSocket, WebSocketDisconnect

from monoloc.core.errors import InvalidInputError, MonolocError
from monoloc.server.api.deps import AppState, StateDep, StreamKey
from monoloc.server.api.errors import error_code
from monoloc.server.api.localizing import localize_bytes, parse_options

log = logging.getLogger(__name__)
router = APIRouter(tags=["stream"])
MAX_HEADER_BYTES = 65536


@dataclass
class _Item:
    seq: int | None
    t: float | None
    data: bytes | None = None  # None: dropped (or an error)
    options: Any = None
    error: dict[str, str] | None = None


def parse_message(message: bytes) -> _Item:
    """Split one binary frame message; an _Item with ``error`` set if malformed."""
    if len(message) < 4:
        return _Item(
            None,
            None,
            error={
                "code": "invalid_input",
                "message": "message shorter than its 4-byte header length",
            },
        )
    (n,) = struct.unpack(">I", message[:4])
    if n > MAX_HEADER_BYTES or 4 + n > len(message):
        return _Item(
            None,
            None,
            error={"code": "invalid_input", "message": f"header length {n} is out of range"},
        )
    try:
        header = json.loads(message[4 : 4 + n].decode("utf-8"))
        if not isinstance(header, dict):
            raise ValueError("the header is not a JSON object")
    except (UnicodeDecodeError, ValueError) as exc:
        return _Item(None, None, error={"code": "invalid_input", "message": f"bad header: {exc}"})
    seq, t = header.get("seq"), header.get("t")
    if not isinstance(seq, int) or isinstance(seq, bool):
        return _Item(
            None,
            None,
            error={"code": "invalid_input", "message": "the header needs an integer 'seq'"},
        )
    item = _Item(seq, float(t) if isinstance(t, int | float) else None)
    try:
        prior = header.get("prior") or {}
        intrinsics = header.get("intrinsics") or {}
        if not isinstance(prior, dict) or not isinstance(intrinsics, dict):
            raise InvalidInputError("'prior' and 'intrinsics' must be objects")
        fields = {f"prior_{k}": v for k, v in prior.items()}
        fields.update({k: intrinsics.get(k) for k in ("fx", "fy", "cx", "cy")})
        fields.update(k=header.get("k"), seed=header.get("seed"))
        item.options = parse_options(fields)
    except MonolocError as exc:
        item.error = {"code": error_code(exc), "message": str(exc)}
        return item
    item.data = message[4 + n :]
    return item


class _Session:
    """The pending answers of one connection, in arrival order."""

    def __init__(self, websocket: WebSocket, state: AppState, map_id: int) -> None:
        self.ws, self.state, self.map_id = websocket, state, map_id
        self.queue: deque[_Item] = deque()
        self.waiting = 0  # items still holding an image
        self.wake = anyio.Event()

    def push(self, item: _Item) -> None:
        if item.data is not None:
            if self.waiting >= self.state.settings.stream_max_pending_frames:
                stale = next(i for i in self.queue if i.data is not None)
                stale.data, stale.options = None, None
                self.waiting -= 1
            self.waiting += 1
        self.queue.append(item)
        self.wake.set()

    async def receive_loop(self) -> None:
        while True:
            message = await self.ws.receive()
            if message["type"] == "websocket.disconnect":
                return
            data = message.get("bytes")
            if data is None:
                item = _Item(
                    None,
                    None,
                    error={
                        "code": "invalid_input",
                        "message": "send binary messages (header + image)",
                    },
                )
            else:
                item = parse_message(data)
            self.push(item)
            if len(self.queue) > self.state.settings.max_stream_backlog:
                await self.ws.close(code=1008, reason="too many frames in flight")
                return

    async def answer(self, item: _Item) -> dict[str, Any]:
        metrics = self.state.metrics.stream_frames
        if item.error is not None:
            metrics.inc("error")
            return {"seq": item.seq, "error": item.error}
        if item.data is None:
            metrics.inc("dropped")
            return {"seq": item.seq, "t": item.t, "dropped": True, "reason": "stale"}
        data, item.data = item.data, None
        self.waiting -= 1
        try:
            result = await localize_bytes(self.state, self.map_id, data, item.options)
        except MonolocError as exc:
            metrics.inc("error")
            error = {"code": error_code(exc), "message": str(exc)}
            return {"seq": item.seq, "t": item.t, "error": error}
        except Exception:  # a bug: answer this frame, keep serving the vehicle
            log.exception("stream of map %s: frame %s failed", self.map_id, item.seq)
            metrics.inc("error")
            error = {"code": "internal_error", "message": "internal error (see the server log)"}
            return {"seq": item.seq, "t": item.t, "error": error}
        metrics.inc("answered")
        return {**result.model_dump(mode="json"), "seq": item.seq, "t": item.t}

    async def send_loop(self, scope: anyio.CancelScope) -> None:
        while True:
            while not self.queue:
                await self.wake.wait()
                self.wake = anyio.Event()
            answer = await self.answer(self.queue[0])
            self.queue.popleft()
            try:
                await self.ws.send_text(json.dumps(answer))
            except Exception:  # the client went away: nobody to answer
                scope.cancel()
                return


@router.websocket("/v1/maps/{map_id}/stream")
async def stream(websocket: WebSocket, map_id: int, state: StateDep, _key: StreamKey) -> None:
    """Frames in, one answer per frame out, in order (see the module docstring)."""
    await anyio.to_thread.run_sync(state.registry.get, map_id)  # 404 before the handshake
    await websocket.accept()
    session = _Session(websocket, state, map_id)
    try:
        async with anyio.create_task_group() as group:
            group.start_soon(session.send_loop, group.cancel_scope)
            await session.receive_loop()
            group.cancel_scope.cancel()
    except* (WebSocketDisconnect, OSError):
        pass  # the client disconnected while we were reading

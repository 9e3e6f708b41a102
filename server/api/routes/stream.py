"""``WS /v1/maps/{map_id}/stream``: one WebSocket per vehicle (localize scope).

Key: header ``X-API-Key`` / ``Authorization: Bearer``, or ``?key=`` (browsers cannot set
WebSocket headers). Refusals happen before the handshake completes, as HTTP answers:
401/403 (key), 404 (map).

In: binary messages, each = 4-byte big-endian header length + UTF-8 JSON header +
encoded image (PNG/JPEG). Header: ``{"seq": int, "t": float, "prior": {"x_m", "y_m",
"radius_m", "yaw_rad"?, "yaw_tolerance_rad"?}?, "k": int?, "seed": int?,
"intrinsics": {"fx", "fy", "cx", "cy", "distortion_model"?, "distortion"?}?,
"camera_id": int?}`` (``camera_id``: a camera registered with ``POST /v1/cameras``,
instead of ``intrinsics``; both: the frame is answered ``invalid_input``, an unknown
id ``not_found``).

Header fields are checked as the localize route's form (``LocalizeOptions``).

Out: one JSON text message per frame, in the order the frames arrived (schemas in
server/api/schemas_localize.py): ``StreamAnswer``, the localize answer plus ``seq`` and
``t``; or ``StreamDropped``, ``{"seq", "t", "dropped": true, "reason": "stale"}`` (or
``"overloaded"``, ``"deadline"``: see back-pressure below); or
``StreamError``, ``{"seq", "t", "error": {"code", "message"}}`` for a frame that could
not be processed (without ``t`` if its header was rejected; a header without a readable
``seq`` gets ``"seq": null``).

A message larger than ``max_query_body_bytes`` (the localize route's body limit) is
answered ``payload_too_large`` without being parsed; the connection stays open.

Back-pressure: at most ``stream_max_pending_frames`` frames wait for processing. When
another arrives, the oldest waiting frame is dropped (its image freed at once) and
answered as dropped when its turn comes, so answers keep arrival order. A frame whose
turn comes enters the localize lane of admission control (server/api/admission.py), as
an HTTP frame does: a full lane drops it at once (``"reason": "overloaded"``), and one
still waiting for a worker ``localize_deadline_ms`` after its arrival is dropped unrun
(``"reason": "deadline"``). A client owed
more than ``max_stream_backlog`` answers is closed with code 1008.
"""

from __future__ import annotations

import json
import logging
import struct
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import anyio
from fastapi import APIRouter, WebSocket, WebSocketDisconnect

from monoloc.core.errors import InvalidInputError, MonolocError, NotFoundError
from monoloc.server.api.admission import DeadlineExceededError
from monoloc.server.api.console.live import VehicleFeed, vehicle_board
from monoloc.server.api.deps import AppState, StateDep, StreamKey
from monoloc.server.api.errors import error_code
from monoloc.server.api.localizing import localize_bytes
from monoloc.server.api.params import is_db_id
from monoloc.server.api.schemas import ErrorDetail
from monoloc.server.api.schemas_localize import (
    LocalizeOptions,
    StreamAnswer,
    StreamDropped,
    StreamError,
)

log = logging.getLogger(__name__)
router = APIRouter(tags=["stream"])
MAX_HEADER_BYTES = 65536


@dataclass
class _Item:
    seq: int | None
    t: float | None
    data: bytes | None = None  # None: dropped (or an error)
    options: LocalizeOptions | None = None
    error: ErrorDetail | None = None
    received_s: float = field(default_factory=time.monotonic)  # for the console's latency


def _rejected(message: str) -> _Item:
    return _Item(None, None, error=ErrorDetail(code="invalid_input", message=message))


def parse_message(message: bytes) -> _Item:
    """Split one binary frame message; an _Item with ``error`` set if malformed."""
    if len(message) < 4:
        return _rejected("message shorter than its 4-byte header length")
    (n,) = struct.unpack(">I", message[:4])
    if n > MAX_HEADER_BYTES or 4 + n > len(message):
        return _rejected(f"header length {n} is out of range")
    try:
        header = json.loads(message[4 : 4 + n].decode("utf-8"))
        if not isinstance(header, dict):
            raise ValueError("the header is not a JSON object")
    except (UnicodeDecodeError, ValueError) as exc:
        return _rejected(f"bad header: {exc}")
    seq, t = header.get("seq"), header.get("t")
    if not isinstance(seq, int) or isinstance(seq, bool):
        return _rejected("the header needs an integer 'seq'")
    item = _Item(seq, float(t) if isinstance(t, int | float) else None)
    try:
        item.options = LocalizeOptions.parse(_option_fields(header))
    except MonolocError as exc:
        item.error = ErrorDetail(code=error_code(exc), message=str(exc))
        return item
    item.data = message[4 + n :]
    return item


def _option_fields(header: dict[str, Any]) -> dict[str, Any]:
    """The header's options as LocalizeOptions' flat fields (``prior.x_m`` -> ``prior_x_m``)."""
    prior = header.get("prior") or {}
    intrinsics = header.get("intrinsics") or {}
    if not isinstance(prior, dict) or not isinstance(intrinsics, dict):
        raise InvalidInputError("'prior' and 'intrinsics' must be objects")
    fields = {f"prior_{k}": v for k, v in prior.items()}
    fields.update({k: intrinsics.get(k) for k in ("fx", "fy", "cx", "cy")})
    fields["distortion_model"] = intrinsics.get("distortion_model")
    coefficients = intrinsics.get("distortion")
    if coefficients is not None:
        if not isinstance(coefficients, list) or not all(
            isinstance(v, int | float) and not isinstance(v, bool) for v in coefficients
        ):
            raise InvalidInputError("'intrinsics.distortion' must be a list of numbers")
        fields["distortion"] = ",".join(repr(float(v)) for v in coefficients)
    fields.update(k=header.get("k"), seed=header.get("seed"), camera_id=header.get("camera_id"))
    return fields


class _Session:
    """The pending answers of one connection, in arrival order."""

    def __init__(
        self, websocket: WebSocket, state: AppState, map_id: int, feed: VehicleFeed
    ) -> None:
        self.ws, self.state, self.map_id, self.feed = websocket, state, map_id, feed
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
            limit = self.state.settings.max_query_body_bytes
            if data is None:
                item = _rejected("send binary messages (header + image)")
            elif len(data) > limit:  # the localize route's limit, answered in order
                detail = f"frame message of {len(data)} bytes exceeds the limit of {limit} bytes"
                item = _Item(
                    None, None, error=ErrorDetail(code="payload_too_large", message=detail)
                )
            else:
                item = parse_message(data)
            self.push(item)
            if len(self.queue) > self.state.settings.max_stream_backlog:
                await self.ws.close(code=1008, reason="too many frames in flight")
                return

    async def answer(self, item: _Item) -> StreamAnswer | StreamDropped | StreamError:
        metrics = self.state.metrics.stream_frames
        if item.error is not None:
            metrics.inc("error")
            return StreamError(seq=item.seq, error=item.error)  # no t: the header was rejected
        if item.data is None or item.options is None:
            metrics.inc("dropped")
            return StreamDropped(seq=item.seq, t=item.t)
        data, item.data = item.data, None
        self.waiting -= 1
        settings = self.state.settings
        deadline_s = item.received_s + settings.localize_deadline_ms / 1e3
        try:
            with self.state.admission.admitted("localize", deadline_s) as admitted:
                if not admitted:  # the lane is full, as it is for HTTP frames: shed
                    metrics.inc("dropped")
                    return StreamDropped(seq=item.seq, t=item.t, reason="overloaded")
                result = await localize_bytes(self.state, self.map_id, data, item.options)
        except DeadlineExceededError:
            metrics.inc("dropped")
            return StreamDropped(seq=item.seq, t=item.t, reason="deadline")
        except MonolocError as exc:
            metrics.inc("error")
            error = ErrorDetail(code=error_code(exc), message=str(exc))
            return StreamError(seq=item.seq, t=item.t, error=error)
        except Exception:  # a bug: answer this frame, keep serving the vehicle
            log.exception("stream of map %s: frame %s failed", self.map_id, item.seq)
            metrics.inc("error")
            error = ErrorDetail(
                code="internal_error", message="internal error (see the server log)"
            )
            return StreamError(seq=item.seq, t=item.t, error=error)
        metrics.inc("answered")
        return StreamAnswer(**result.model_dump(), seq=item.seq, t=item.t)

    async def send_loop(self, scope: anyio.CancelScope) -> None:
        while True:
            while not self.queue:
                await self.wake.wait()
                self.wake = anyio.Event()
            item = self.queue[0]
            answer = await self.answer(item)
            self.queue.popleft()
            # exclude_unset: an error answer leaves out the t it was not given
            body = answer.model_dump(mode="json", exclude_unset=isinstance(answer, StreamError))
            self.feed.report(body, item.received_s, item.options.prior if item.options else None)
            self.state.metrics.count_stream_answer(self.map_id, body)
            try:
                await self.ws.send_text(json.dumps(body))
            except Exception:  # the client went away: nobody to answer
                scope.cancel()
                return


@router.websocket("/v1/maps/{map_id}/stream")
async def stream(websocket: WebSocket, map_id: int, state: StateDep, _key: StreamKey) -> None:
    """Frames in, one answer per frame out, in order (see the module docstring)."""
    if not is_db_id(map_id):  # the driver cannot hold it: no such map
        raise NotFoundError(f"map {map_id} does not exist")
    await anyio.to_thread.run_sync(state.registry.get, map_id)  # 404 before the handshake
    await websocket.accept()
    feed = vehicle_board(websocket.app).connect(map_id, _key.name)
    session = _Session(websocket, state, map_id, feed)
    try:
        async with anyio.create_task_group() as group:
            group.start_soon(session.send_loop, group.cancel_scope)
            await session.receive_loop()
            group.cancel_scope.cancel()
    except* (WebSocketDisconnect, OSError):
        pass  # the client disconnected while we were reading
    finally:
        feed.close()

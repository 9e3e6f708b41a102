"""The WebSocket stream under malformed input (issue 15, "keep it closed"): every bad
message (too short, lying header lengths, non-JSON or non-object headers, wrong types,
out-of-range options, text instead of binary, hostile images, oversized frames) gets
its own error answer, in order, and the connection keeps serving good frames."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from api_helpers import frame_png, live_server, make_settings

from monoloc.client.api import FrameStream, ServerError
from monoloc.server.api.params import DB_ID_MAX


def _message(header: object, image: bytes = b"", *, raw_header: bytes | None = None) -> bytes:
    body = raw_header if raw_header is not None else json.dumps(header).encode()
    return struct.pack(">I", len(body)) + body + image


def _hostile_messages(png: bytes, max_bytes: int, rng: np.random.Generator) -> list[bytes | str]:
    seq = {"seq": 0, "t": 0.0}
    return [
        b"",
        b"\x00\x00",
        struct.pack(">I", 10**9) + b"{}",  # header length beyond the message
        struct.pack(">I", 5) + b"{}",  # header length beyond the message, by a little
        _message(None, raw_header=b"\xff\xfe not utf-8"),
        _message(None, raw_header=b"{not json"),
        _message([1, 2, 3]),
        _message({"t": 1.0}, png),  # no seq
        _message({"seq": "7"}, png),
        _message({"seq": True}, png),
        _message({"seq": 1.5}, png),
        _message({**seq, "k": 0}, png),
        _message({**seq, "k": "ten"}, png),
        _message({**seq, "seed": -1}, png),
        _message({**seq, "seed": 2**64}, png),
        _message({**seq, "prior": "here"}, png),
        _message({**seq, "prior": {"x_m": 1.0}}, png),  # incomplete group
        _message({**seq, "prior": {"x_m": 1.0, "y_m": 2.0, "radius_m": -5}}, png),
        _message({**seq, "intrinsics": {"fx": 1.0}}, png),
        _message({**seq, "intrinsics": [1, 2]}, png),
        _message(seq, b""),  # no image
        _message(seq, b"GIF89a" + bytes(rng.integers(0, 256, 200, dtype=np.uint8))),
        _message(seq, png[: len(png) // 3]),  # truncated PNG
        _message(seq, b"\x89PNG\r\n\x1a\n" + b"\x00" * (max_bytes + 1)),  # oversized frame
        "a text message",
        bytes(rng.integers(0, 256, 4096, dtype=np.uint8)),
    ]


@pytest.fixture
def stream_server(map_copy):
    settings = make_settings(map_copy.data_dir, stream_max_pending_frames=64)
    with live_server(settings) as port:
        yield port, settings


def test_every_malformed_message_gets_an_error_and_the_stream_keeps_serving(
    sim_dataset, map_copy, stream_server
):
    from websockets.sync.client import connect

    port, settings = stream_server
    png = frame_png(sim_dataset, "01", 4)
    rng = np.random.default_rng(15)
    hostile = _hostile_messages(png, settings.max_query_body_bytes, rng)
    url = f"ws://127.0.0.1:{port}/v1/maps/{map_copy.map_id}/stream"
    headers = {"X-API-Key": map_copy.keys.localize}
    with connect(url, additional_headers=headers, max_size=None, open_timeout=30) as ws:
        for i, message in enumerate(hostile):
            ws.send(message)
            answer = json.loads(ws.recv(timeout=60))
            assert "error" in answer, (i, answer)
            assert answer["error"]["code"] and answer["error"]["message"], (i, answer)
            assert answer["error"]["code"] != "internal_error", (i, answer)
            # ... and the connection still serves a good frame right after.
            ws.send(_message({"seq": 1000 + i, "t": float(i)}, png))
            good = json.loads(ws.recv(timeout=60))
            assert good["seq"] == 1000 + i and "hypotheses" in good, (i, good)


def test_stream_with_an_id_beyond_int64_is_not_found(map_copy, stream_server):
    port, _ = stream_server
    for map_id in (DB_ID_MAX + 1, 10**30):
        with pytest.raises(ServerError, match="404"):
            FrameStream(f"http://127.0.0.1:{port}", map_copy.keys.localize, map_id, timeout_s=30)

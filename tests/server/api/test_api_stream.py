"""The WebSocket stream over a real uvicorn, driven by the vehicle's own client
(monoloc.client.api.FrameStream): answers in order with seq preserved, per-frame errors in
place, and stale frames dropped (and said so) when the client floods."""

from __future__ import annotations

import json
import logging
import struct
import threading
import time

import numpy as np
import pytest
from api_helpers import frame_png, ground_truth, live_server, make_settings

from monoloc.client.api import FrameStream, ServerError
from monoloc.core.geometry import planar_from_T_world_from_cam
from monoloc.core.prior import RetrievalPrior
from monoloc.server.api.app import create_app


def _stream(port: int, key: str, map_id: int) -> FrameStream:
    return FrameStream(f"http://127.0.0.1:{port}", key, map_id, timeout_s=30.0)


def test_round_trip_in_order_with_errors_in_place(sim_dataset, map_copy):
    settings = make_settings(map_copy.data_dir, stream_max_pending_frames=16)
    frames = [2, 4, 6, 8]
    with (
        live_server(settings) as port,
        _stream(port, map_copy.keys.localize, map_copy.map_id) as stream,
    ):
        stream.send(0, 0.0, frame_png(sim_dataset, "01", frames[0]))
        stream._ws.send(struct.pack(">I", 500) + b"{}")  # header length out of range
        stream.send(1, 0.1, b"GIF89a not an image")
        for seq, frame in enumerate(frames[1:], start=2):
            truth = planar_from_T_world_from_cam(ground_truth(sim_dataset, "01", frame))
            prior = RetrievalPrior(float(truth[0]), float(truth[1]), 20.0)
            stream.send(seq, seq / 10, frame_png(sim_dataset, "01", frame), prior=prior, k=5)
        answers = [stream.receive() for _ in range(6)]
    assert [a["seq"] for a in answers] == [0, None, 1, 2, 3, 4]
    assert answers[1]["error"]["code"] == "invalid_input"
    assert answers[2]["error"]["code"] == "unsupported_media_type"
    assert "t" not in answers[1] and answers[2]["t"] == pytest.approx(0.1)  # t once queued
    for answer, frame in zip([answers[0], *answers[3:]], frames, strict=True):
        truth = planar_from_T_world_from_cam(ground_truth(sim_dataset, "01", frame))
        assert answer["hypotheses"], (frame, answer["rejected_entries"], answer["n_features"])
        best = answer["hypotheses"][0]
        assert np.hypot(best["pose"]["x_m"] - truth[0], best["pose"]["y_m"] - truth[1]) < 0.5
        assert answer["map_version"] > 0 and "dropped" not in answer
    assert answers[3]["t"] == pytest.approx(0.2) and len(answers[3]["retrieved"]) <= 5


def test_flooding_drops_the_oldest_frames_and_says_so(sim_dataset, map_copy, monkeypatch):
    import monoloc.server.api.routes.stream as stream_route

    settings = make_settings(map_copy.data_dir, stream_max_pending_frames=2)
    app = create_app(settings)
    n = 12
    # A server that falls behind: nothing is localized before every frame has arrived
    # (an event, not a sleep: the outcome must not depend on how busy the machine is).
    arrived = threading.Event()
    pushed: list = []
    push = stream_route._Session.push

    def counting_push(session, item):
        push(session, item)
        pushed.append(item.seq)
        if len(pushed) == n:
            arrived.set()

    monkeypatch.setattr(stream_route._Session, "push", counting_push)
    with live_server(settings, app) as port:
        registry = app.state.monoloc.registry
        original = registry.localize

        def slow_localize(*args, **kwargs):
            assert arrived.wait(60), "the frames did not arrive"
            return original(*args, **kwargs)

        registry.localize = slow_localize
        image = frame_png(sim_dataset, "01", 5)
        with _stream(port, map_copy.keys.localize, map_copy.map_id) as stream:
            for seq in range(n):
                stream.send(seq, seq * 0.01, image)
            answers = [stream.receive() for _ in range(n)]
        dropped_metric = app.state.monoloc.metrics.stream_frames.value("dropped")
    assert [a["seq"] for a in answers] == list(range(n))
    dropped = [a["seq"] for a in answers if a.get("dropped")]
    processed = [a["seq"] for a in answers if "hypotheses" in a]
    assert len(dropped) + len(processed) == n
    assert all(a["reason"] == "stale" for a in answers if a.get("dropped"))
    assert len(dropped) >= n - 4, answers  # at most ~2 waiting + 1 in flight + 1 racing
    assert processed[-2:] == [n - 2, n - 1]  # the newest frames are never the stale ones
    assert dropped_metric == len(dropped)


def test_stream_frames_share_the_localize_lane_and_its_deadline(sim_dataset, map_copy):
    # one worker, no queue: one frame (HTTP or stream) inside the lane at a time
    settings = make_settings(
        map_copy.data_dir, worker_threads=1, localize_queue_depth=0, localize_deadline_ms=300
    )
    app = create_app(settings)
    image = frame_png(sim_dataset, "01", 5)
    with (
        live_server(settings, app) as port,
        _stream(port, map_copy.keys.localize, map_copy.map_id) as stream,
    ):
        state = app.state.monoloc
        lane = state.admission.lanes["localize"]
        assert lane.try_enter()  # an HTTP frame holds the lane's only place
        try:
            start = time.perf_counter()
            stream.send(0, 0.0, image)
            full = stream.receive()
            assert time.perf_counter() - start < 0.25  # shed at once, not queued
        finally:
            lane.leave()
        release = threading.Event()
        busy = lane.submit(release.wait)  # the worker is busy past the frame's deadline
        try:
            start = time.perf_counter()
            stream.send(1, 0.1, image)
            late = stream.receive()
            waited_s = time.perf_counter() - start
        finally:
            release.set()
        assert busy.result(10) is True
        stream.send(2, 0.2, image)
        served = stream.receive()
        shed = state.metrics.admission_shed.value("localize")
        expired = state.metrics.admission_expired.value("localize", "deadline")
    assert full == {"seq": 0, "t": 0.0, "dropped": True, "reason": "overloaded"}
    assert late == {"seq": 1, "t": 0.1, "dropped": True, "reason": "deadline"}
    assert 0.3 <= waited_s < 3.0
    assert served["seq"] == 2 and served["hypotheses"] and "dropped" not in served
    assert (shed, expired) == (1, 1)


def test_stream_refuses_a_missing_key_and_a_missing_map(map_copy):
    with live_server(make_settings(map_copy.data_dir)) as port:
        with pytest.raises(ServerError, match="401"):
            _stream(port, "", map_copy.map_id)
        with pytest.raises(ServerError, match="404"):
            _stream(port, map_copy.keys.localize, 999)


def test_client_leaving_mid_stream_and_query_key_not_logged(sim_dataset, map_copy, caplog):
    from websockets.sync.client import connect

    from monoloc.client.api import encode_frame

    image = frame_png(sim_dataset, "01", 9)
    key = map_copy.keys.localize
    uvicorn_logger = logging.getLogger("uvicorn")
    with live_server(make_settings(map_copy.data_dir), log_level="info") as port:
        uvicorn_logger.addHandler(caplog.handler)  # after uvicorn configured its logging
        try:
            with _stream(port, key, map_copy.map_id) as stream:
                for seq in range(3):
                    stream.send(seq, 0.0, image)
            # gone without reading: the server must cope, and serve the next vehicle
            url = f"ws://127.0.0.1:{port}/v1/maps/{map_copy.map_id}/stream?key={key}"
            with connect(url, max_size=2**24) as ws:
                ws.send(encode_frame({"seq": 9}, image))
                answer = json.loads(ws.recv(timeout=30))
        finally:
            uvicorn_logger.removeHandler(caplog.handler)
    assert answer["seq"] == 9 and answer["hypotheses"]
    assert "stream?key=***" in caplog.text  # the connection was logged, redacted
    assert key not in caplog.text and key[4:] not in caplog.text
    assert "Exception in ASGI application" not in caplog.text

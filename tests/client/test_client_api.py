"""MonolocClient's failure handling, with failures injected by httpx.MockTransport (and a
port nobody listens on): retries with growing backoff on 5xx / 429 / transport errors,
the server's Retry-After, and 4xx raised at once with the server's message. The normal
paths run against a real server in tests/e2e/test_e2e_client_http.py."""

from __future__ import annotations

import json
import socket
import struct
import time

import httpx
import numpy as np
import pytest

from monoloc.client.api import LocalizeAnswer, MonolocClient, ServerError, encode_frame
from monoloc.core.errors import InvalidInputError, NotFoundError
from monoloc.core.prior import RetrievalPrior

OK_ANSWER = {
    "map_id": 1,
    "map_version": 3,
    "hypotheses": [
        {
            "entry_id": 7,
            "pose": {"x_m": 1.0, "y_m": 2.0, "yaw_rad": 0.1},
            "entry_pose": {"x_m": 1.5, "y_m": 2.5, "yaw_rad": 0.2},
            "e_vlad": 0.8,
            "n_inliers": 40,
        }
    ],
    "timings_ms": {"total": 12.5},
}


class Script:
    """A fake server answering from a list of (status, json body | exception), recording
    when each request arrived."""

    def __init__(self, steps):
        self.steps = list(steps)
        self.times: list[float] = []
        self.requests: list[httpx.Request] = []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        self.times.append(time.perf_counter())
        self.requests.append(request)
        step = self.steps.pop(0) if len(self.steps) > 1 else self.steps[0]
        if isinstance(step, Exception):
            raise step
        status, body, *headers = step
        return httpx.Response(status, json=body, headers=headers[0] if headers else None)

    def client(self, **kwargs) -> MonolocClient:
        kwargs.setdefault("backoff_s", 0.0)
        return MonolocClient(
            "http://fake", "mlk_test", transport=httpx.MockTransport(self), **kwargs
        )


def _error(message: str, code: str = "x") -> dict:
    return {"error": {"code": code, "message": message}}


def test_5xx_is_retried_with_doubling_backoff_then_succeeds():
    script = Script([(503, _error("starting")), (502, _error("proxy")), (200, OK_ANSWER)])
    with script.client(retries=3, backoff_s=0.05) as client:
        answer = client.localize(1, b"\x89PNG\r\n\x1a\nfake")
    assert len(script.times) == 3
    gaps = np.diff(script.times)
    assert gaps[0] >= 0.05 and gaps[1] >= 0.10  # backoff_s * 2**attempt
    assert gaps[1] > 1.5 * gaps[0]
    assert answer.map_version == 3 and len(answer.hypotheses) == 1
    assert script.requests[0].headers["X-API-Key"] == "mlk_test"


def test_persistent_5xx_gives_up_with_the_server_message_after_all_attempts():
    script = Script([(500, _error("database is locked", "internal_error"))])
    with script.client(retries=2) as client, pytest.raises(ServerError) as info:
        client.request("GET", "/v1/maps")
    assert len(script.times) == 3
    assert info.value.status_code == 500
    assert "database is locked" in str(info.value) and "3 attempts" in str(info.value)


def test_retry_after_of_a_429_is_honoured_and_capped():
    script = Script([(429, _error("slow down"), {"Retry-After": "0.2"}), (200, {"items": []})])
    with script.client(retries=1) as client:
        client.request("GET", "/v1/maps")
    assert script.times[1] - script.times[0] >= 0.2
    capped = Script([(503, _error("busy"), {"Retry-After": "600"}), (200, {"items": []})])
    start = time.perf_counter()
    with capped.client(retries=1, max_backoff_s=0.05) as client:
        client.request("GET", "/v1/maps")
    assert time.perf_counter() - start < 60


@pytest.mark.parametrize(
    ("status", "error_type"),
    [(400, ServerError), (401, ServerError), (403, ServerError), (404, NotFoundError),
     (405, ServerError), (413, ServerError), (422, ServerError), (501, ServerError)],
)  # fmt: skip
def test_4xx_and_501_raise_at_once_with_the_server_message(status, error_type):
    script = Script([(status, _error(f"reason number {status}")), (200, OK_ANSWER)])
    with script.client(retries=3, backoff_s=1.0) as client, pytest.raises(error_type) as info:
        client.localize(1, b"img")
    assert len(script.times) == 1  # no retry, no backoff
    assert f"{status} reason number {status}" in str(info.value)
    if error_type is ServerError:
        assert info.value.status_code == status


def test_timeouts_and_refused_connections_are_retried():
    script = Script([httpx.ReadTimeout("too slow"), (200, {"items": [{"id": 4, "name": "a"}]})])
    with script.client(retries=1) as client:
        assert client.find_map_id("a") == 4
    assert len(script.times) == 2
    with socket.socket() as sock:  # a port with nobody listening: real ECONNREFUSED
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    start = time.perf_counter()
    with MonolocClient(f"http://127.0.0.1:{port}", "k", retries=2, backoff_s=0.05) as client:
        with pytest.raises(ServerError, match="ConnectError.*3 attempts"):
            client.request("GET", "/healthz")
    assert time.perf_counter() - start >= 0.05 + 0.10


def test_error_bodies_that_are_not_monoloc_json_still_give_a_message():
    def plain(request):
        return httpx.Response(502, text="Bad Gateway from nginx")

    def detail(request):
        return httpx.Response(422, json={"detail": [{"loc": ["body", "k"], "msg": "bad k"}]})

    with MonolocClient("http://x", "k", retries=0, transport=httpx.MockTransport(plain)) as c:
        with pytest.raises(ServerError, match="502 Bad Gateway from nginx"):
            c.request("GET", "/")
    with MonolocClient("http://x", "k", transport=httpx.MockTransport(detail)) as c:
        with pytest.raises(ServerError, match="422 .*bad k"):
            c.request("GET", "/")


def test_settings_are_checked():
    with pytest.raises(InvalidInputError, match="retries"):
        MonolocClient("http://x", "k", retries=-1)


def test_localize_sends_prior_k_and_seed_as_form_fields():
    script = Script([(200, OK_ANSWER)])
    with script.client() as client:
        client.localize(5, b"img", prior=RetrievalPrior(1.5, -2.0, 8.0, 0.3, 0.4), k=4, seed=11)
    request = script.requests[0]
    assert request.url.path == "/v1/maps/5/localize"
    body = request.content.decode("latin-1")
    for name, value in [
        ("prior_x_m", "1.5"),
        ("prior_y_m", "-2.0"),
        ("prior_radius_m", "8.0"),
        ("prior_yaw_rad", "0.3"),
        ("prior_yaw_tolerance_rad", "0.4"),
        ("k", "4"),
        ("seed", "11"),
    ]:
        assert f'name="{name}"\r\n\r\n{value}\r\n' in body


def test_answers_parse_into_hypotheses_and_malformed_ones_are_refused():
    answer = LocalizeAnswer.from_json(OK_ANSWER)
    np.testing.assert_allclose(answer.hypotheses.pose_world, [[1.0, 2.0, 0.1]])
    np.testing.assert_allclose(answer.hypotheses.entry_pose_world, [[1.5, 2.5, 0.2]])
    np.testing.assert_allclose(answer.hypotheses.e_vlad, [0.8])
    empty = LocalizeAnswer.from_json({"hypotheses": [], "map_version": 1})
    assert len(empty.hypotheses) == 0 and empty.hypotheses.pose_world.shape == (0, 3)
    broken = {"hypotheses": [{"pose": {"x_m": 1.0, "y_m": 2.0}}]}
    with pytest.raises(ServerError, match="malformed"):
        LocalizeAnswer.from_json(broken)


def test_stream_messages_follow_the_wire_format():
    prior = RetrievalPrior(1.0, 2.0, 10.0)
    message = encode_frame({"seq": 3, "t": 0.3, "prior": prior.to_json()}, b"IMAGE")
    (n,) = struct.unpack(">I", message[:4])
    header = json.loads(message[4 : 4 + n])
    assert header == {"seq": 3, "t": 0.3, "prior": {"x_m": 1.0, "y_m": 2.0, "radius_m": 10.0}}
    assert message[4 + n :] == b"IMAGE"


def test_opening_a_stream_is_retried_when_nobody_answers():
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    start = time.perf_counter()
    with MonolocClient(f"http://127.0.0.1:{port}", "k", retries=2, backoff_s=0.05) as client:
        with pytest.raises(ServerError, match="cannot open the stream.*3 attempts") as info:
            client.stream(1, timeout_s=2.0)
    assert info.value.status_code is None
    assert time.perf_counter() - start >= 0.05 + 0.10


def test_wait_until_ready_stops_when_the_server_process_exits_or_times_out():
    import socket
    import subprocess
    import sys

    from monoloc.client.api import wait_until_ready

    with socket.socket() as sock:  # a port nothing listens on
        sock.bind(("127.0.0.1", 0))
        url = f"http://127.0.0.1:{sock.getsockname()[1]}"
    exited = subprocess.Popen([sys.executable, "-c", "raise SystemExit(3)"])
    exited.wait(30)
    with pytest.raises(ServerError, match="exited with code 3"):
        wait_until_ready(url, 30.0, exited)
    with pytest.raises(ServerError, match="not ready within"):
        wait_until_ready(url, 0.3, poll_s=0.05)

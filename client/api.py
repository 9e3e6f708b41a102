"""HTTP and WebSocket client of the map server, as a vehicle uses it.

Timeouts on every call, retries with exponential backoff on connection errors and 5xx /
429 answers, and the wire format of the stream: one binary message per frame made of a
4-byte big-endian header length, a UTF-8 JSON header and the encoded image.
"""

from __future__ import annotations

import json
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass

import httpx
import numpy as np

from client.errors import InvalidInputError, MonolocError, NotFoundError
from client.measurement import Hypotheses, MeasurementModel


class ServerError(MonolocError):
    """The server answered with an error, or could not be reached after retries."""

    def __init__(self, message: str, status_code: int | None = None) -> None:
        super().__init__(message)
        self.status_code = status_code


@dataclass(frozen=True)
class Prior:
    """Retrieval prior sent with a frame: only map entries inside compete."""

    x_m: float
    y_m: float
    radius_m: float
    yaw_rad: float | None = None
    yaw_tolerance_rad: float | None = None

    def to_fields(self) -> dict[str, float]:
        fields = {"prior_x_m": self.x_m, "prior_y_m": self.y_m, "prior_radius_m": self.radius_m}
        if self.yaw_rad is not None and self.yaw_tolerance_rad is not None:
            fields["prior_yaw_rad"] = self.yaw_rad
            fields["prior_yaw_tolerance_rad"] = self.yaw_tolerance_rad
        return fields

    def to_json(self) -> dict[str, float]:
        return {key.removeprefix("prior_"): value for key, value in self.to_fields().items()}


@dataclass(frozen=True)
class LocalizeAnswer:
    """The server's answer for one frame."""

    hypotheses: Hypotheses
    map_version: int | None
    timings_ms: dict[str, float]
    raw: dict

    @classmethod
    def from_json(cls, data: dict) -> LocalizeAnswer:
        try:
            hyps = data.get("hypotheses") or []
            pose = np.array(
                [[h["pose"]["x_m"], h["pose"]["y_m"], h["pose"]["yaw_rad"]] for h in hyps],
                dtype=np.float64,
            ).reshape(-1, 3)
            entry = np.array(
                [
                    [h["entry_pose"]["x_m"], h["entry_pose"]["y_m"], h["entry_pose"]["yaw_rad"]]
                    for h in hyps
                ],
                dtype=np.float64,
            ).reshape(-1, 3)
            e_vlad = np.array([h["e_vlad"] for h in hyps], dtype=np.float64)
        except (KeyError, TypeError) as exc:
            raise ServerError(f"malformed localize answer: missing {exc}") from exc
        return cls(
            hypotheses=Hypotheses(pose, entry, e_vlad),
            map_version=data.get("map_version"),
            timings_ms=dict(data.get("timings_ms") or {}),
            raw=data,
        )


def _error_message(response: httpx.Response) -> str:
    try:
        body = response.json()
        err = body.get("error", body)
        return str(err.get("message", err)) if isinstance(err, dict) else str(err)
    except ValueError:
        return response.text[:200]


class MonolocClient:
    """Synchronous client. ``transport`` lets tests and in-process callers inject one."""

    def __init__(
        self,
        base_url: str,
        api_key: str,
        timeout_s: float = 10.0,
        retries: int = 3,
        backoff_s: float = 0.2,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        self.base_url = base_url.rstrip("/")
        self.api_key = api_key
        self.retries = retries
        self.backoff_s = backoff_s
        self._http = httpx.Client(
            base_url=self.base_url,
            headers={"X-API-Key": api_key},
            timeout=timeout_s,
            transport=transport,
        )

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> MonolocClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def request(self, method: str, path: str, **kwargs) -> httpx.Response:
        """One call with retries on transport errors, 429 and 5xx; raises on 4xx."""
        last: Exception | None = None
        for attempt in range(self.retries + 1):
            try:
                response = self._http.request(method, path, **kwargs)
            except httpx.TransportError as exc:
                last = ServerError(f"{method} {path}: {exc.__class__.__name__}: {exc}")
            else:
                if response.status_code < 400:
                    return response
                message = f"{method} {path}: {response.status_code} {_error_message(response)}"
                if response.status_code == 404:
                    raise NotFoundError(message)
                if response.status_code in (400, 401, 403, 409, 413, 415, 422):
                    raise ServerError(message, response.status_code)
                last = ServerError(message, response.status_code)
            if attempt < self.retries:
                time.sleep(self.backoff_s * (2**attempt))
        assert last is not None
        raise last

    def find_map_id(self, name_or_id: str | int) -> int:
        """A map's id from its id or its name."""
        if isinstance(name_or_id, int) or str(name_or_id).isdigit():
            return int(name_or_id)
        maps = self.request("GET", "/v1/maps").json()
        items = maps["items"] if isinstance(maps, dict) and "items" in maps else maps
        for item in items:
            if item.get("name") == name_or_id:
                return int(item["id"])
        raise NotFoundError(f"no map named {name_or_id!r} on {self.base_url}")

    def localize(
        self,
        map_id: int,
        image_bytes: bytes,
        prior: Prior | None = None,
        k: int | None = None,
        filename: str = "frame.png",
    ) -> LocalizeAnswer:
        data: dict[str, str] = {}
        if prior is not None:
            data.update({key: repr(float(v)) for key, v in prior.to_fields().items()})
        if k is not None:
            data["k"] = str(int(k))
        mime = "image/jpeg" if filename.lower().endswith((".jpg", ".jpeg")) else "image/png"
        response = self.request(
            "POST",
            f"/v1/maps/{map_id}/localize",
            files={"image": (filename, image_bytes, mime)},
            data=data,
        )
        return LocalizeAnswer.from_json(response.json())

    def measurement_model(self, map_id: int) -> tuple[MeasurementModel, bool]:
        """The map's calibrated measurement model, and whether it was calibrated."""
        data = self.request("GET", f"/v1/maps/{map_id}/calibration").json()
        return MeasurementModel.from_dict(data), bool(data.get("calibrated", False))

    def stream(self, map_id: int, timeout_s: float = 30.0) -> FrameStream:
        return FrameStream(self.base_url, self.api_key, map_id, timeout_s)


def encode_frame(header: dict, image_bytes: bytes) -> bytes:
    """One stream message: 4-byte big-endian header length, JSON header, image bytes."""
    head = json.dumps(header, separators=(",", ":")).encode()
    return struct.pack(">I", len(head)) + head + image_bytes


class FrameStream:
    """A WebSocket stream of frames to one map; answers come back in order."""

    def __init__(self, base_url: str, api_key: str, map_id: int, timeout_s: float) -> None:
        from websockets.sync.client import connect

        url = base_url.replace("https://", "wss://").replace("http://", "ws://")
        self._timeout_s = timeout_s
        try:
            self._ws = connect(
                f"{url}/v1/maps/{map_id}/stream",
                additional_headers={"X-API-Key": api_key},
                open_timeout=timeout_s,
                max_size=2**24,
            )
        except Exception as exc:  # noqa: BLE001 - any failure to connect is one error here
            raise ServerError(f"cannot open the stream to map {map_id}: {exc}") from exc

    def send(
        self,
        seq: int,
        t_s: float,
        image_bytes: bytes,
        prior: Prior | None = None,
        k: int | None = None,
    ) -> None:
        header: dict = {"seq": seq, "t": t_s}
        if prior is not None:
            header["prior"] = prior.to_json()
        if k is not None:
            header["k"] = k
        self._ws.send(encode_frame(header, image_bytes))

    def receive(self) -> dict:
        """The next answer (a localize answer, or {"seq", "dropped": true, ...})."""
        try:
            message = self._ws.recv(timeout=self._timeout_s)
        except TimeoutError as exc:
            raise ServerError("the stream answered nothing in time") from exc
        data = json.loads(message)
        if "error" in data and "seq" not in data:
            raise ServerError(f"stream error: {data['error']}")
        return data

    def answers(self) -> Iterator[dict]:
        while True:
            yield self.receive()

    def close(self) -> None:
        self._ws.close()

    def __enter__(self) -> FrameStream:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def check_image_bytes(data: bytes, name: str) -> bytes:
    """Refuse anything that is not PNG or JPEG before sending it."""
    if not (data.startswith(b"\x89PNG\r\n\x1a\n") or data.startswith(b"\xff\xd8\xff")):
        raise InvalidInputError(f"{name} is not a PNG or JPEG image")
    return data

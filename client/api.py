"""HTTP and WebSocket client of the map server, as a vehicle uses it.

Timeouts on every call; retries with exponential backoff (or the server's
``Retry-After``) on connection errors, timeouts, 408, 429 and 5xx answers except 501;
any other 4xx is raised at once with the server's message. The stream's wire format:
one binary message per frame made of a 4-byte big-endian header length, a UTF-8 JSON
header and the encoded image.
"""

from __future__ import annotations

import json
import math
import struct
import time
from collections.abc import Iterator
from contextlib import ExitStack
from dataclasses import dataclass

import httpx
import numpy as np

from monoloc.core.camera import CameraIntrinsics, LensDistortion
from monoloc.core.errors import InvalidInputError, MonolocError, NotFoundError
from monoloc.core.geo import GeoReference
from monoloc.core.measurement import Hypotheses, MeasurementModel
from monoloc.core.prior import RetrievalPrior


class ServerError(MonolocError):
    """The server answered with an error, or could not be reached after retries."""

    def __init__(
        self, message: str, status_code: int | None = None, retry_after_s: float | None = None
    ) -> None:
        super().__init__(message)
        self.status_code = status_code
        self.retry_after_s = retry_after_s  # the server's Retry-After (503 shed, 429)


@dataclass(frozen=True)
class LocalizeAnswer:
    """The server's answer for one frame. A frame the stream dropped (``dropped``) or
    could not process (``error``: "code: message") has no hypotheses."""

    hypotheses: Hypotheses
    map_version: int | None
    timings_ms: dict[str, float]
    raw: dict
    dropped: bool = False
    error: str | None = None

    @property
    def best_pose_world(self) -> np.ndarray:
        """Pose (3,) of the per-entry hypothesis with the most PnP inliers (a joint one
        aside); NaN without one."""
        best = self._best_raw()
        if best is None:
            return np.full(3, np.nan)
        return np.array([best["pose"]["x_m"], best["pose"]["y_m"], best["pose"]["yaw_rad"]])

    @property
    def best_geopose(self) -> dict | None:
        """The OGC GeoPose ({"position": {lat, lon, h}, "quaternion": {x, y, z, w}}) of the
        hypothesis ``best_pose_world`` gives, when the map is geo-referenced; else None."""
        best = self._best_raw()
        return None if best is None else best.get("geopose")

    @property
    def best_height_m(self) -> float:
        """World z (m) of the camera centre of the hypothesis ``best_pose_world`` gives
        (its ``T_world_from_cam``); NaN without one."""
        best = self._best_raw()
        T = (best or {}).get("T_world_from_cam")
        if not isinstance(T, list) or len(T) != 16:
            return math.nan
        return float(T[11])  # row 2, column 3 of the row-major 4x4

    def _best_raw(self) -> dict | None:
        hyps = [h for h in self.raw.get("hypotheses") or [] if not h.get("joint", False)]
        return max(hyps, key=lambda h: h.get("n_inliers", 0)) if hyps else None

    @classmethod
    def from_stream(cls, data: dict) -> LocalizeAnswer:
        """One answer of the WebSocket stream: a localize answer, a dropped frame or a
        frame the server answered with an error."""
        if data.get("dropped"):
            return cls(Hypotheses.empty(), None, {}, data, dropped=True)
        if "error" in data:
            err = data["error"]
            if isinstance(err, dict):
                message = f"{err.get('code', 'error')}: {err.get('message', '')}"
            else:
                message = str(err)
            return cls(Hypotheses.empty(), None, {}, data, error=message)
        return cls.from_json(data)

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
            quality = _quality_features(hyps)
            covariance = _pose_covariances(hyps)
            tags = tuple(tuple(str(t) for t in h.get("entry_tags") or ()) for h in hyps)
            # how each pose was found (a server before the field: unknown)
            method = (
                tuple(str(h["method"]) for h in hyps) if all("method" in h for h in hyps) else None
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ServerError(f"malformed localize answer: missing {exc}") from exc
        return cls(
            hypotheses=Hypotheses(
                pose,
                entry,
                e_vlad,
                *quality,
                pose_covariance=covariance,
                entry_tags=tags,
                method=method,
            ),
            map_version=data.get("map_version"),
            timings_ms=dict(data.get("timings_ms") or {}),
            raw=data,
        )


def _quality_features(hyps: list[dict]) -> tuple[np.ndarray | None, ...]:
    """(n_inliers, reprojection_error_px, joint) arrays of the answer's hypotheses; None
    for a feature some hypothesis lacks (a server older than the quality model)."""
    if not hyps or not all("n_inliers" in h and "reprojection_error_px" in h for h in hyps):
        return None, None, None
    n_inliers = np.array([h["n_inliers"] for h in hyps], dtype=np.float64)
    error_px = np.array([h["reprojection_error_px"] for h in hyps], dtype=np.float64)
    joint = np.array([bool(h.get("joint", False)) for h in hyps], dtype=bool)
    return n_inliers, error_px, joint


def _pose_covariances(hyps: list[dict]) -> np.ndarray | None:
    """(H, 3, 3) planar pose covariances at 1 px of the answer's hypotheses, NaN for one
    without (joint, pooled); None when no hypothesis has one (a server older than them)."""
    if not any(h.get("pose_covariance") is not None for h in hyps):
        return None
    out = np.full((len(hyps), 3, 3), np.nan)
    for i, h in enumerate(hyps):
        if h.get("pose_covariance") is not None:
            out[i] = np.asarray(h["pose_covariance"], dtype=np.float64).reshape(3, 3)
    return out


def wait_until_ready(base_url: str, timeout_s: float, process=None, poll_s: float = 0.2) -> None:
    """Return once ``GET {base_url}/readyz`` answers 200. ``process`` (a
    ``subprocess.Popen`` of the server, optional): stop waiting as soon as it exits.
    Raises ServerError when the server exits or is not ready within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        if process is not None and process.poll() is not None:
            raise ServerError(f"the server at {base_url} exited with code {process.returncode}")
        try:
            if httpx.get(f"{base_url}/readyz", timeout=2.0).status_code == 200:
                return
        except httpx.TransportError:
            pass
        if time.monotonic() > deadline:
            raise ServerError(f"the server at {base_url} was not ready within {timeout_s:.0f} s")
        time.sleep(poll_s)


# Answers worth another try: the request may succeed later (the server is starting,
# overloaded, restarting behind a proxy). 501 means "never in this build".
RETRY_STATUS = frozenset({408, 429, 500, 502, 503, 504})
# A wait (the server's Retry-After or the backoff) is lengthened by up to this share, drawn
# per wait: clients told the same wait at the same moment (a proxy's fixed Retry-After,
# a server restart) do not all come back in the same millisecond. Retry-After is the
# least wait the server asked for, so the jitter only adds.
RETRY_JITTER = 0.25


def jittered_wait_s(wait_s: float, rng: np.random.Generator) -> float:
    """``wait_s`` lengthened by a uniform draw of up to ``RETRY_JITTER`` of it."""
    return wait_s * (1.0 + RETRY_JITTER * float(rng.random()))


def _error_message(response: httpx.Response) -> str:
    """The server's own message: ``{"error": {"message"}}``, FastAPI's ``{"detail"}``, or
    the start of the body."""
    try:
        body = response.json()
    except ValueError:
        return response.text[:200].strip() or response.reason_phrase
    if isinstance(body, dict):
        err = body.get("error", body.get("detail", body))
        if isinstance(err, dict) and "message" in err:
            return str(err["message"])
        return str(err)[:500]
    return str(body)[:500]


def _retry_after_s(response: httpx.Response | None) -> float | None:
    """Seconds to wait: the server's ``Retry-After-Ms`` (milliseconds; monoloc sends it
    beside the whole seconds of ``Retry-After``) when valid, else a numeric
    ``Retry-After``; None if neither."""
    if response is None:
        return None
    for name, scale in (("retry-after-ms", 1e-3), ("retry-after", 1.0)):
        try:
            value = float(response.headers.get(name, ""))
        except ValueError:
            continue
        if value >= 0 and math.isfinite(value):
            return value * scale
    return None


class MonolocClient:
    """Synchronous client. ``transport`` lets tests and in-process callers inject one;
    ``rng`` draws the retry waits' jitter (default: seeded from OS entropy)."""

    def __init__(
        self,
        base_url: str,
        api_key: str,
        timeout_s: float = 10.0,
        retries: int = 3,
        backoff_s: float = 0.2,
        transport: httpx.BaseTransport | None = None,
        max_backoff_s: float = 10.0,
        rng: np.random.Generator | None = None,
    ) -> None:
        if retries < 0 or backoff_s < 0 or max_backoff_s < 0:
            raise InvalidInputError(
                f"retries, backoff_s and max_backoff_s must be >= 0, got {retries}, "
                f"{backoff_s}, {max_backoff_s}"
            )
        self.base_url = base_url.rstrip("/")
        self.api_key = api_key
        self.retries = retries
        self.backoff_s = backoff_s
        self.max_backoff_s = max_backoff_s
        self._rng = np.random.default_rng() if rng is None else rng
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

    def request(
        self, method: str, path: str, retries: int | None = None, **kwargs
    ) -> httpx.Response:
        """One call; retried (``retries`` more times, default the client's, waiting
        ``backoff_s * 2**attempt``, or the server's ``Retry-After``, plus up to
        ``RETRY_JITTER`` of it, capped at ``max_backoff_s``) on transport errors
        and RETRY_STATUS answers. Other 4xx/5xx raise at once: NotFoundError for 404,
        ServerError (with ``status_code``) otherwise, both with the server's message."""
        retries = self.retries if retries is None else retries
        last: ServerError | None = None
        for attempt in range(retries + 1):
            response = None
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
                if response.status_code not in RETRY_STATUS:
                    raise ServerError(message, response.status_code)
                last = ServerError(message, response.status_code, _retry_after_s(response))
            if attempt < retries:
                wait = _retry_after_s(response)
                if wait is None:
                    wait = self.backoff_s * (2**attempt)
                time.sleep(min(jittered_wait_s(wait, self._rng), self.max_backoff_s))
        assert last is not None
        raise ServerError(
            f"{last} (gave up after {retries + 1} attempts)", last.status_code, last.retry_after_s
        ) from last

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
        prior: RetrievalPrior | None = None,
        k: int | None = None,
        filename: str = "frame.png",
        seed: int | None = None,
        *,
        intrinsics: CameraIntrinsics | None = None,
        camera_id: int | None = None,
        retries: int | None = None,
        deadline_ms: int | None = None,
        min_map_version: int | None = None,
    ) -> LocalizeAnswer:
        """Hypotheses for one PNG/JPEG frame over HTTP (``seed``: the server's RANSAC
        seed, to repeat an answer; default: the server draws one). ``deadline_ms``: how
        long the answer is worth waiting for (the server drops the frame uncomputed
        after it); ``min_map_version``: answer from a map at least this new (after one's
        own write; the server waits briefly for its replica, else 503); ``retries``:
        this call's retries (a vehicle sends 0: a frame is stale by the next one);
        ``intrinsics``: the camera that took the frame, or ``camera_id`` the id it was
        registered under (:meth:`camera_id`); neither: the map's camera."""
        data: dict[str, str] = {}
        if camera_id is not None:
            data["camera_id"] = str(int(camera_id))
        if intrinsics is not None:
            data.update({key: repr(float(v)) for key, v in _focal(intrinsics).items()})
            if intrinsics.distortion is not None:
                data["distortion_model"] = intrinsics.distortion.model
                data["distortion"] = ",".join(repr(v) for v in intrinsics.distortion.coefficients)
        if prior is not None:
            data.update({key: repr(float(v)) for key, v in prior.to_fields().items()})
        if k is not None:
            data["k"] = str(int(k))
        if seed is not None:
            data["seed"] = str(int(seed))
        mime = "image/jpeg" if filename.lower().endswith((".jpg", ".jpeg")) else "image/png"
        headers: dict[str, str] = {}
        if deadline_ms is not None:
            headers["X-Request-Deadline-Ms"] = str(int(deadline_ms))
        if min_map_version is not None:
            headers["X-Min-Map-Version"] = str(int(min_map_version))
        response = self.request(
            "POST",
            f"/v1/maps/{map_id}/localize",
            retries=retries,
            files={"image": (filename, image_bytes, mime)},
            data=data,
            headers=headers,
        )
        return LocalizeAnswer.from_json(response.json())

    def register_camera(self, name: str, intrinsics: CameraIntrinsics) -> int:
        """Register a camera (``POST /v1/cameras``, scope localize); its id, which frames
        then send as ``camera_id`` instead of the intrinsics."""
        body = {"name": name, **_focal(intrinsics), **_lens_fields(intrinsics)}
        body.update(width_px=int(intrinsics.width_px), height_px=int(intrinsics.height_px))
        return int(self.request("POST", "/v1/cameras", json=body).json()["id"])

    def cameras(self) -> list[tuple[int, str, CameraIntrinsics]]:
        """The registered cameras: (id, name, intrinsics) each."""
        items = self.request("GET", "/v1/cameras").json()["items"]
        return [(int(c["id"]), str(c["name"]), camera_from_json(c)) for c in items]

    def delete_camera(self, camera_id: int) -> None:
        self.request("DELETE", f"/v1/cameras/{int(camera_id)}")

    def camera_id(self, intrinsics: CameraIntrinsics, name: str | None = None) -> int:
        """The id of a registered camera equal to ``intrinsics`` (and named ``name``, by
        default :func:`camera_name`), registering it first if there is none: a vehicle's
        camera is registered once, not once per drive."""
        name = camera_name(intrinsics) if name is None else name
        for camera_id, other_name, other in self.cameras():
            if other_name == name and other == intrinsics:
                return camera_id
        return self.register_camera(name, intrinsics)

    def measurement_model(self, map_id: int) -> tuple[MeasurementModel, bool]:
        """The map's calibrated measurement model, and whether it was calibrated."""
        data = self.request("GET", f"/v1/maps/{map_id}/calibration").json()
        return MeasurementModel.from_dict(data), bool(data.get("calibrated", False))

    def geo_reference(self, map_id: int) -> GeoReference | None:
        """The map's geographic reference (``GET /v1/maps/{id}/geo-reference``, scope
        localize), or None when the map has none (the route's 404; a missing map has
        already failed on any other call by then). A reference the server sends that
        does not parse raises ServerError."""
        try:
            data = self.request("GET", f"/v1/maps/{map_id}/geo-reference").json()
        except NotFoundError:
            return None
        if not isinstance(data, dict):
            raise ServerError(f"malformed geo reference of map {map_id}: {str(data)[:100]}")
        try:
            return GeoReference.from_dict(data)
        except (InvalidInputError, TypeError, ValueError) as exc:
            raise ServerError(f"malformed geo reference of map {map_id}: {exc}") from exc

    def stream(self, map_id: int, timeout_s: float = 30.0) -> FrameStream:
        """Open the map's WebSocket stream, retried like :meth:`request` when the server
        cannot be reached or answers a RETRY_STATUS; 401/403/404 raise at once."""
        for attempt in range(self.retries + 1):
            try:
                return FrameStream(self.base_url, self.api_key, map_id, timeout_s)
            except ServerError as exc:
                final = exc.status_code is not None and exc.status_code not in RETRY_STATUS
                if final or attempt == self.retries:
                    if attempt:
                        raise ServerError(
                            f"{exc} (gave up after {attempt + 1} attempts)", exc.status_code
                        ) from exc
                    raise
            time.sleep(min(self.backoff_s * (2**attempt), self.max_backoff_s))
        raise AssertionError("unreachable")


def _focal(intrinsics: CameraIntrinsics) -> dict[str, float]:
    """fx, fy, cx, cy (px) as the localize form and the stream header take them."""
    return {
        "fx": float(intrinsics.fx),
        "fy": float(intrinsics.fy),
        "cx": float(intrinsics.cx),
        "cy": float(intrinsics.cy),
    }


def camera_name(intrinsics: CameraIntrinsics) -> str:
    """A name that describes a camera (size, focal length, lens), the same for equal ones."""
    lens = intrinsics.distortion
    return (
        f"{intrinsics.width_px}x{intrinsics.height_px} f{intrinsics.fx:.1f}"
        f"{'' if lens is None else ' ' + lens.model}"
    )


def camera_from_json(data: dict) -> CameraIntrinsics:
    """A camera as the registry answers it (``CameraPublic``)."""
    lens = LensDistortion.parse(data.get("distortion_model"), data.get("distortion"))
    return CameraIntrinsics(
        float(data["fx"]),
        float(data["fy"]),
        float(data["cx"]),
        float(data["cy"]),
        int(data["width_px"]),
        int(data["height_px"]),
        lens,
    )


def _lens_fields(intrinsics: CameraIntrinsics) -> dict:
    """The lens distortion as the stream header takes it (model, coefficient list)."""
    lens = intrinsics.distortion
    if lens is None:
        return {}
    return {"distortion_model": lens.model, "distortion": list(lens.coefficients)}


def encode_frame(header: dict, image_bytes: bytes) -> bytes:
    """One stream message: 4-byte big-endian header length, JSON header, image bytes."""
    head = json.dumps(header, separators=(",", ":")).encode()
    return struct.pack(">I", len(head)) + head + image_bytes


class FrameStream:
    """A WebSocket stream of frames to one map; answers come back in order.

    The connection is opened as the context manager websockets documents (entered on an
    ``ExitStack`` that :meth:`close` unwinds), so it works the same with websockets 12
    through 17+. No permessage-deflate: frames are PNG/JPEG already, and deflating them
    again only adds round-trip time (bench/speed.py).
    """

    def __init__(self, base_url: str, api_key: str, map_id: int, timeout_s: float) -> None:
        from websockets.sync.client import connect

        url = base_url.replace("https://", "wss://").replace("http://", "ws://")
        self._timeout_s = timeout_s
        self._exits = ExitStack()
        try:
            self._ws = self._exits.enter_context(
                connect(
                    f"{url}/v1/maps/{map_id}/stream",
                    additional_headers={"X-API-Key": api_key},
                    open_timeout=timeout_s,
                    max_size=2**24,
                    compression=None,
                )
            )
        except Exception as exc:  # noqa: BLE001 - any failure to connect is one error here
            # websockets' InvalidStatus carries the HTTP answer that refused the handshake
            status = getattr(getattr(exc, "response", None), "status_code", None)
            raise ServerError(f"cannot open the stream to map {map_id}: {exc}", status) from exc

    def send(
        self,
        seq: int,
        t_s: float,
        image_bytes: bytes,
        prior: RetrievalPrior | None = None,
        k: int | None = None,
        seed: int | None = None,
        intrinsics: CameraIntrinsics | None = None,
        camera_id: int | None = None,
    ) -> None:
        """Send one frame (PNG/JPEG bytes) with its sequence number and time (s), and the
        camera that took it: its intrinsics, or the id it was registered under (neither:
        the map's)."""
        header: dict = {"seq": seq, "t": t_s}
        if camera_id is not None:
            header["camera_id"] = int(camera_id)
        if intrinsics is not None:
            header["intrinsics"] = {**_focal(intrinsics), **_lens_fields(intrinsics)}
        if prior is not None:
            header["prior"] = prior.to_json()
        if k is not None:
            header["k"] = k
        if seed is not None:
            header["seed"] = int(seed)
        try:
            self._ws.send(encode_frame(header, image_bytes))
        except Exception as exc:  # noqa: BLE001 - closed socket, reset connection, ...
            raise ServerError(f"the stream is closed, cannot send frame {seq}: {exc}") from exc

    def receive(self) -> dict:
        """The next answer (a localize answer, ``{"seq", "dropped": true, ...}`` or
        ``{"seq", "error": {...}}`` for a frame the server could not process)."""
        try:
            message = self._ws.recv(timeout=self._timeout_s)
        except TimeoutError as exc:
            raise ServerError(f"the stream answered nothing within {self._timeout_s} s") from exc
        except Exception as exc:  # noqa: BLE001 - the connection closed under us
            raise ServerError(f"the stream closed: {exc}") from exc
        try:
            data = json.loads(message)
        except ValueError as exc:
            raise ServerError(f"the stream sent a non-JSON answer: {message[:100]!r}") from exc
        if not isinstance(data, dict):
            raise ServerError(f"the stream sent a non-object answer: {str(data)[:100]}")
        if "error" in data and "seq" not in data:
            raise ServerError(f"stream error: {data['error']}")
        return data

    def answers(self) -> Iterator[dict]:
        while True:
            yield self.receive()

    def close(self) -> None:
        self._exits.close()

    def __enter__(self) -> FrameStream:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

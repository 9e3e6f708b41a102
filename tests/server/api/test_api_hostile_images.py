"""A generated corpus of hostile images against localize, entries and the stream: bombs by
pixel count and by compression ratio, truncated PNG and JPEG, foreign formats, 1-pixel
sides, 16-bit and RGBA images of the wrong size. Each gets a 4xx with a clear message
(the stream: an error answer in place, the connection still usable), and nothing is
stored."""

from __future__ import annotations

import io
import json
import struct
import zlib

import cv2
import numpy as np
import pytest
from api_helpers import create_keys, live_server, make_settings, open_client
from PIL import Image
from skimage import data as skdata

from monoloc.client.api import FrameStream

CAMERA = dict(fx=300.0, fy=300.0, cx=159.5, cy=119.5, width_px=320, height_px=240)


def _chunk(kind: bytes, payload: bytes) -> bytes:
    crc = struct.pack(">I", zlib.crc32(kind + payload))
    return struct.pack(">I", len(payload)) + kind + payload + crc


def _png(width: int, height: int, stream: bytes, depth: int = 8, color: int = 0) -> bytes:
    ihdr = struct.pack(">IIBBBBB", width, height, depth, color, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", ihdr)
        + _chunk(b"IDAT", stream)
        + _chunk(b"IEND", b"")
    )


def _zeros_stream(n_bytes: int) -> bytes:
    deflate = zlib.compressobj(9)
    block = bytes(1 << 20)
    parts = [deflate.compress(block) for _ in range(n_bytes >> 20)]
    return b"".join([*parts, deflate.flush()])


def _encode(image: np.ndarray, ext: str) -> bytes:
    ok, data = cv2.imencode(ext, image)
    assert ok
    return data.tobytes()


def _pil(image: np.ndarray, fmt: str) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format=fmt)
    return buffer.getvalue()


def hostile_corpus() -> dict[str, tuple[bytes, set[int]]]:
    """name -> (bytes, accepted status codes)."""
    photo = skdata.camera()[:240, :320]
    png, jpeg = _encode(photo, ".png"), _encode(photo, ".jpg")
    return {
        "pixel bomb (PNG header 60000x60000)": (_png(60000, 60000, b""), {413}),
        "ratio bomb (camera-sized PNG inflating to 64 MB)": (
            _png(320, 240, _zeros_stream(64 << 20)),
            {422},
        ),
        "truncated PNG": (png[: len(png) // 2], {422}),
        "truncated JPEG": (jpeg[: len(jpeg) // 3], {422}),
        "GIF": (_pil(photo, "GIF"), {415}),
        "BMP": (_pil(photo, "BMP"), {415}),
        "TIFF": (_pil(photo, "TIFF"), {415}),
        "WebP": (_pil(photo, "WEBP"), {415}),
        "1 pixel high": (_encode(photo[:1], ".png"), {422}),
        "1 pixel wide": (_encode(photo[:, :1], ".png"), {422}),
        "16-bit RGBA, wrong size": (
            _encode(np.zeros((480, 640, 4), np.uint16), ".png"),
            {422},
        ),
        "RGBA, wrong size": (_encode(np.zeros((100, 100, 4), np.uint8), ".png"), {422}),
        "empty": (b"", {415, 422}),
    }


CORPUS = hostile_corpus()


@pytest.fixture
def served_map(tmp_path):
    settings = make_settings(tmp_path / "data")
    with open_client(settings) as client:
        keys = create_keys(client)
        r = client.post(
            "/v1/maps", json={"name": "m", "camera": CAMERA}, headers=keys.header("admin")
        )
        assert r.status_code == 201, r.text
        yield client, keys, r.json()["id"], settings


def _message(response) -> str:
    return response.json()["error"]["message"]


@pytest.mark.parametrize("name", list(CORPUS))
def test_localize_refuses_each_hostile_image(served_map, name):
    client, keys, map_id, _ = served_map
    data, statuses = CORPUS[name]
    with_intrinsics = {"fx": "300", "fy": "300", "cx": "0.5", "cy": "0.5"}
    # With its own intrinsics a frame may have any size: "wrong size" is no longer wrong.
    variants = [{}] if "wrong size" in name else [{}, with_intrinsics]
    for extra in variants:
        r = client.post(
            f"/v1/maps/{map_id}/localize",
            headers=keys.header("localize"),
            files={"image": ("f.png", data, "image/png")},
            data=extra,
        )
        assert r.status_code in statuses, (name, extra, r.status_code, r.text)
        assert len(_message(r)) > 10


@pytest.mark.parametrize("name", list(CORPUS))
def test_entries_refuse_each_hostile_image_and_store_nothing(served_map, name):
    client, keys, map_id, _ = served_map
    data, statuses = CORPUS[name]
    pose = json.dumps(np.eye(4).ravel().tolist())
    scan = np.array([[0.0, 0.0, 5.0, 1.0]] * 10, dtype="<f4").tobytes()
    r = client.post(
        f"/v1/maps/{map_id}/entries",
        headers=keys.header("write"),
        files={"image": ("a.png", data, "image/png"), "lidar": ("s.bin", scan, "x")},
        data={"T_world_from_cam": pose, "T_cam_from_lidar": pose},
    )
    assert r.status_code in statuses, (name, r.status_code, r.text)
    assert len(_message(r)) > 10
    listed = client.get(f"/v1/maps/{map_id}/entries", headers=keys.header("write")).json()
    assert listed["total"] == 0


def test_the_stream_answers_each_hostile_frame_in_place_and_stays_usable(served_map):
    _, keys, map_id, settings = served_map
    good = _encode(skdata.camera()[:240, :320], ".png")
    names = [n for n in CORPUS if CORPUS[n][0]]  # the client refuses to send empty frames
    with (
        live_server(settings) as port,
        FrameStream(f"http://127.0.0.1:{port}", keys.localize, map_id, timeout_s=30.0) as s,
    ):
        answers = []
        for seq, data in enumerate([*(CORPUS[n][0] for n in names), good]):
            s.send(seq, float(seq), data)  # one at a time: a flood would drop stale frames
            answers.append(s.receive())
    for name, answer in zip(names, answers[:-1], strict=True):
        assert "error" in answer, (name, answer)
        assert answer["error"]["code"] in {
            "invalid_input",
            "payload_too_large",
            "unsupported_media_type",
        }, (name, answer)
        assert len(answer["error"]["message"]) > 10
    assert "error" not in answers[-1] and answers[-1]["seq"] == len(names), answers[-1]

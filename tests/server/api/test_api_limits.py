"""Limits: body size while receiving (declared and chunked, over a real uvicorn), image
type by magic bytes, pixel count from the header, malformed fields; every refusal is
JSON and stores nothing."""

from __future__ import annotations

import json
import socket
import struct
import zlib

import cv2
import numpy as np
import pytest
from api_helpers import ADMIN_KEY, create_keys, live_server, make_settings, open_client

from monoloc.core.errors import InvalidInputError
from monoloc.server.api.errors import PayloadTooLargeError, UnsupportedMediaTypeError
from monoloc.server.api.limits import check_image

CAMERA = dict(fx=300.0, fy=300.0, cx=159.5, cy=119.5, width_px=320, height_px=240)


def png_header(width: int, height: int, depth: int = 8, color: int = 0) -> bytes:
    """A PNG signature + IHDR chunk (no image data): enough for the header check."""
    ihdr = struct.pack(">IIBBBBB", width, height, depth, color, 0, 0, 0)
    chunk = b"IHDR" + ihdr
    return (
        b"\x89PNG\r\n\x1a\n"
        + struct.pack(">I", len(ihdr))
        + chunk
        + struct.pack(">I", zlib.crc32(chunk))
    )


def jpeg_bytes(width: int = 40, height: int = 30) -> bytes:
    ok, data = cv2.imencode(".jpg", np.full((height, width), 128, np.uint8))
    assert ok
    return data.tobytes()


def test_header_check_reads_size_without_decoding():
    assert check_image(png_header(640, 480), "x", 10**6).width_px == 640
    info = check_image(jpeg_bytes(80, 64), "x", 10**6)
    assert (info.kind, info.width_px, info.height_px) == ("jpeg", 80, 64)
    huge = bytearray(jpeg_bytes(80, 64))
    sof = huge.index(b"\xff\xc0")
    huge[sof + 5 : sof + 9] = struct.pack(">HH", 60000, 60000)
    with pytest.raises(PayloadTooLargeError, match="60000x60000"):
        check_image(bytes(huge), "x", 25_000_000)
    with pytest.raises(UnsupportedMediaTypeError):
        check_image(b"GIF89a" + bytes(100), "x", 10**6)
    with pytest.raises(InvalidInputError):
        check_image(b"\x89PNG\r\n\x1a\n" + bytes(4), "x", 10**6)
    with pytest.raises(InvalidInputError):
        check_image(b"\xff\xd8\xff\xd9", "x", 10**6)


@pytest.fixture
def small(tmp_path):
    """An app with a 256 KiB body limit and one empty map."""
    settings = make_settings(tmp_path / "data", max_body_bytes=256 * 1024)
    with open_client(settings) as client:
        keys = create_keys(client)
        r = client.post(
            "/v1/maps", json={"name": "m", "camera": CAMERA}, headers=keys.header("admin")
        )
        yield client, keys, r.json()["id"]


def _localize(client, map_id, keys, image: bytes, **data):
    return client.post(
        f"/v1/maps/{map_id}/localize",
        headers=keys.header("localize"),
        files={"image": ("f.png", image, "image/png")},
        data=data,
    )


def test_declared_body_over_the_limit_is_413(small):
    client, keys, map_id = small
    r = _localize(client, map_id, keys, bytes(300 * 1024))
    assert r.status_code == 413
    assert r.json()["error"]["code"] == "payload_too_large"


def test_image_type_pixels_and_fields(small):
    client, keys, map_id = small
    cases = [
        (b"GIF89a" + bytes(64), {}, 415, "unsupported_media_type"),
        (png_header(30000, 30000), {}, 413, "payload_too_large"),
        (png_header(320, 240) + b"garbage", {}, 422, "invalid_input"),
        (png_header(640, 480), {}, 422, "invalid_input"),  # not the map camera's size
        (png_header(320, 240), {"prior_x_m": "1"}, 422, "invalid_input"),
        (png_header(320, 240), {"k": "0"}, 422, "invalid_input"),
        (png_header(320, 240), {"fx": "300"}, 422, "invalid_input"),
        (png_header(320, 240), {"k": "ten"}, 422, "validation_error"),
    ]
    for image, data, status, code in cases:
        r = _localize(client, map_id, keys, image, **data)
        assert r.status_code == status, (data, r.text)
        assert r.json()["error"]["code"] == code and r.json()["error"]["message"]
    assert (
        client.post(
            f"/v1/maps/{map_id}/localize",
            headers=keys.header("localize"),
        ).status_code
        == 422
    )  # no image at all


def test_entry_refusals_store_nothing(small):
    client, keys, map_id = small
    url, h = f"/v1/maps/{map_id}/entries", keys.header("write")
    pose = json.dumps(np.eye(4).ravel().tolist())
    image = cv2.imencode(".png", np.zeros((240, 320), np.uint8))[1].tobytes()
    depth8 = cv2.imencode(".png", np.zeros((240, 320), np.uint8))[1].tobytes()
    cases = [
        ({"image": ("a.gif", b"GIF89a..", "image/gif")}, {"T_world_from_cam": pose}, 415),
        ({"image": ("a.png", image, "image/png")}, {"T_world_from_cam": pose}, 422),  # no 3D
        (
            {"image": ("a.png", image, "image/png"), "depth": ("d.png", depth8, "image/png")},
            {"T_world_from_cam": pose, "depth_scale": "1000"},
            422,
        ),  # 8-bit depth
        (
            {"image": ("a.png", image, "image/png"), "lidar": ("s.bin", bytes(15), "x")},
            {"T_world_from_cam": pose, "T_cam_from_lidar": pose},
            422,
        ),  # not 16-byte points
        (
            {"image": ("a.png", image, "image/png"), "lidar": ("s.bin", bytes(160), "x")},
            {"T_world_from_cam": "[1, 2, 3]", "T_cam_from_lidar": pose},
            422,
        ),
        (
            {"image": ("a.png", image, "image/png"), "lidar": ("s.bin", bytes(160), "x")},
            {
                "T_world_from_cam": json.dumps((2 * np.eye(4)).ravel().tolist()),
                "T_cam_from_lidar": pose,
            },
            422,
        ),  # not rigid
    ]
    for files, data, status in cases:
        r = client.post(url, files=files, data=data, headers=h)
        assert r.status_code == status, (data, r.text)
    m = client.get(f"/v1/maps/{map_id}", headers=keys.header("admin")).json()
    assert m["n_entries"] == 0 and m["version"] == 0


def _read_response(sock: socket.socket) -> tuple[int, bytes]:
    """Status and body of one HTTP/1.1 answer with a Content-Length."""
    data = b""
    sock.settimeout(10)
    while b"\r\n\r\n" not in data:
        part = sock.recv(65536)
        if not part:
            break
        data += part
    head, _, body = data.partition(b"\r\n\r\n")
    length = 0
    for line in head.split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        if name.strip().lower() == b"content-length":
            length = int(value)
    while len(body) < length:
        part = sock.recv(65536)
        if not part:
            break
        body += part
    return int(head.split()[1]), body


def test_chunked_body_is_cut_off_while_receiving(tmp_path):
    limit = 256 * 1024
    with live_server(make_settings(tmp_path / "data", max_body_bytes=limit)) as port:
        with socket.create_connection(("127.0.0.1", port)) as sock:
            preamble = (
                b'--b\r\nContent-Disposition: form-data; name="image"; '
                b'filename="f.png"\r\nContent-Type: image/png\r\n\r\n'
            )
            sock.sendall(
                b"POST /v1/maps/1/localize HTTP/1.1\r\nHost: t\r\n"
                + f"X-API-Key: {ADMIN_KEY}\r\n".encode()
                + b"Content-Type: multipart/form-data; boundary=b\r\n"
                + b"Transfer-Encoding: chunked\r\n\r\n"
                + f"{len(preamble):x}\r\n".encode()
                + preamble
                + b"\r\n"
            )
            sent, chunk = len(preamble), b"\x89PNG" + bytes(16 * 1024 - 4)
            while sent <= limit:  # never finished: the server must answer mid-body
                sock.sendall(f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n")
                sent += len(chunk)
            status, body = _read_response(sock)
        assert status == 413
        assert b"payload_too_large" in body
        # A declared Content-Length over the limit is refused before any body is sent.
        with socket.create_connection(("127.0.0.1", port)) as sock:
            sock.sendall(
                b"POST /v1/maps/1/localize HTTP/1.1\r\nHost: t\r\n"
                + f"Content-Length: {10 * limit}\r\n\r\n".encode()
            )
            assert _read_response(sock)[0] == 413

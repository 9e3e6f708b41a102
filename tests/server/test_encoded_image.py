"""Decoding work is bounded by what an image's header declares: compression bombs, truncated
streams and hostile ancillary chunks are refused or dropped before OpenCV inflates them;
real photographs pass through unchanged."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest
from skimage import data as skdata

from monoloc.core.errors import InvalidInputError
from monoloc.server import encoded_image
from monoloc.server.encoded_image import (
    MAX_JPEG_SCANS,
    bounded_for_decoding,
    bounded_png,
    png_filtered_size,
)


def _chunk(kind: bytes, payload: bytes) -> bytes:
    return (
        struct.pack(">I", len(payload))
        + kind
        + payload
        + struct.pack(">I", zlib.crc32(kind + payload))
    )


def _png(width: int, height: int, stream: bytes, extra: bytes = b"", depth=8, color=0) -> bytes:
    ihdr = struct.pack(">IIBBBBB", width, height, depth, color, 0, 0, 0)
    return (
        encoded_image.PNG_SIGNATURE
        + _chunk(b"IHDR", ihdr)
        + extra
        + _chunk(b"IDAT", stream)
        + _chunk(b"IEND", b"")
    )


def _zeros_stream(n_bytes: int) -> bytes:
    """zlib stream of n_bytes zero bytes, made in 1 MB pieces (ratio ~1000:1)."""
    deflate = zlib.compressobj(9)
    block = bytes(1 << 20)
    out = [deflate.compress(block) for _ in range(n_bytes >> 20)]
    out.append(deflate.compress(bytes(n_bytes & ((1 << 20) - 1))))
    out.append(deflate.flush())
    return b"".join(out)


@pytest.fixture(scope="module")
def photo_gray() -> np.ndarray:
    return skdata.camera()[:376, :500]


def test_real_photographs_decode_exactly_as_before(photo_gray):
    rgb = skdata.astronaut()
    for image in (photo_gray, rgb, (photo_gray.astype(np.uint16) * 257)):
        encoded = cv2.imencode(".png", image)[1].tobytes()
        guarded = bounded_png(encoded, "x")
        expected = cv2.imdecode(np.frombuffer(encoded, np.uint8), cv2.IMREAD_UNCHANGED)
        got = cv2.imdecode(np.frombuffer(guarded, np.uint8), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(got, expected)
    jpeg = cv2.imencode(".jpg", rgb, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes()
    assert bounded_for_decoding(jpeg, "x") == jpeg  # a real progressive JPEG passes


def test_a_camera_sized_png_that_inflates_to_hundreds_of_megabytes_is_refused(monkeypatch):
    width, height = 1241, 376
    needed = png_filtered_size(width, height, 8, 0, False)
    assert needed == height * (width + 1)
    bomb = _png(width, height, _zeros_stream(200 << 20))
    assert len(bomb) < 400_000
    inflated = []
    real = zlib.decompressobj

    class Counting:
        def __init__(self):
            self._inner = real()

        def decompress(self, data, max_length=0):
            out = self._inner.decompress(data, max_length)
            inflated.append(len(out))
            return out

        def __getattr__(self, name):
            return getattr(self._inner, name)

    monkeypatch.setattr(encoded_image.zlib, "decompressobj", Counting)
    with pytest.raises(InvalidInputError, match="inflates beyond"):
        bounded_png(bomb, "image")
    assert sum(inflated) <= needed + 1  # never inflated past what the header needs


def test_a_stream_that_ends_short_or_is_corrupt_is_refused():
    width, height = 100, 80
    short = _png(width, height, zlib.compress(bytes(height * (width + 1) - 10)))
    with pytest.raises(InvalidInputError, match="ends after"):
        bounded_png(short, "image")
    with pytest.raises(InvalidInputError, match="corrupt"):
        bounded_png(_png(width, height, b"\x78\x9c" + b"\xff" * 50), "image")
    truncated = _png(width, height, zlib.compress(bytes(height * (width + 1))))[:-20]
    with pytest.raises(InvalidInputError, match="truncated"):
        bounded_png(truncated, "image")


def test_compressed_ancillary_chunks_are_dropped_not_inflated(photo_gray):
    encoded = cv2.imencode(".png", photo_gray)[1].tobytes()
    # A zTXt chunk holding a 100 MB text: libpng would inflate it.
    ztxt = _chunk(b"zTXt", b"Comment\x00\x00" + _zeros_stream(100 << 20))
    hostile = encoded[:33] + ztxt + encoded[33:]
    guarded = bounded_png(hostile, "image")
    # what is left: the headers and the image's own scanlines (stored, not re-compressed)
    raw_size = png_filtered_size(photo_gray.shape[1], photo_gray.shape[0], 8, 0, False)
    assert b"zTXt" not in guarded and len(guarded) <= raw_size + 1024
    got = cv2.imdecode(np.frombuffer(guarded, np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(got, photo_gray)


def test_interlaced_size_counts_each_adam7_pass():
    # 8x8 gray: passes of 1x1, 1x1, 2x1, 2x2, 4x2, 4x4, 8x4 pixels (one filter byte a row).
    rows = [(1, 1), (1, 1), (2, 1), (2, 2), (4, 2), (4, 4), (8, 4)]
    assert png_filtered_size(8, 8, 8, 0, True) == sum(h * (1 + w) for w, h in rows)
    # 1x1 RGBA 16-bit: only the first pass has a pixel.
    assert png_filtered_size(1, 1, 16, 6, True) == 1 + 8


def test_invalid_headers_are_refused():
    stream = zlib.compress(bytes(10 * 11))
    with pytest.raises(InvalidInputError, match="invalid PNG header"):
        bounded_png(_png(10, 10, stream, depth=3), "image")
    with pytest.raises(InvalidInputError, match="0x10"):
        bounded_png(_png(0, 10, stream), "image")


def test_a_jpeg_with_too_many_scans_is_refused():
    jpeg = cv2.imencode(".jpg", np.full((64, 64), 90, np.uint8))[1].tobytes()
    sos = jpeg.index(b"\xff\xda")
    # Repeat the scan header: each one a full pass for a progressive decoder.
    hostile = jpeg[:sos] + jpeg[sos : sos + 14] * (MAX_JPEG_SCANS + 1) + jpeg[sos:]
    with pytest.raises(InvalidInputError, match="scans"):
        bounded_for_decoding(hostile, "image")

"""The mono camera PNG (8-bit grayscale, not interlaced) is unfiltered by monoloc itself
from the stream it inflates to bound the work: pixels identical to OpenCV's decoder for
every filter type and for files written by OpenCV and Pillow; any other PNG is left to
OpenCV; a row with an unknown filter type is refused."""

from __future__ import annotations

import io
import struct
import zlib

import cv2
import numpy as np
import pytest
from PIL import Image
from skimage import data as skdata

from monoloc.core.errors import InvalidInputError
from monoloc.server.api.limits import check_image, decode_gray
from monoloc.server.encoded_image import PNG_SIGNATURE, png_gray8_pixels


def _chunk(kind: bytes, payload: bytes) -> bytes:
    crc = zlib.crc32(kind + payload)
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", crc)


def _png_of_rows(width: int, filtered_rows: bytes, height: int, extra: bytes = b"") -> bytes:
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (
        PNG_SIGNATURE
        + _chunk(b"IHDR", ihdr)
        + extra
        + _chunk(b"IDAT", zlib.compress(filtered_rows, 6))
        + _chunk(b"IEND", b"")
    )


def _opencv(data: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)


def test_every_filter_type_unfilters_as_opencv_does():
    rng = np.random.default_rng(7)
    width, height = 97, 60
    rows = rng.integers(0, 256, size=(height, 1 + width), dtype=np.uint8)
    rows[:, 0] = np.arange(height) % 5  # filter types 0-4, each after each
    data = _png_of_rows(width, rows.tobytes(), height)
    pixels = png_gray8_pixels(data, "image")
    expected = _opencv(data)
    assert expected is not None and pixels is not None
    assert pixels.shape == (height, width)
    np.testing.assert_array_equal(pixels, expected)


@pytest.mark.parametrize("writer", ["opencv-1", "opencv-9", "pillow-optimize"])
def test_real_photographs_from_the_fields_writers_decode_identically(writer):
    gray = skdata.camera()[:, :480]  # not a multiple of 8 wide
    if writer.startswith("opencv"):
        level = int(writer.split("-")[1])
        ok, buf = cv2.imencode(".png", gray, [cv2.IMWRITE_PNG_COMPRESSION, level])
        assert ok
        data = buf.tobytes()
    else:
        out = io.BytesIO()
        Image.fromarray(gray).save(out, format="PNG", optimize=True)
        data = out.getvalue()
    pixels = png_gray8_pixels(data, "image")
    assert pixels is not None
    np.testing.assert_array_equal(pixels, gray)
    info = check_image(data, "image", 10**8)
    np.testing.assert_array_equal(decode_gray(data, info, "image"), gray)


def test_other_pngs_are_left_to_opencv():
    rgb = skdata.astronaut()[:64, :64]
    ok, colour = cv2.imencode(".png", rgb)
    ok16, deep = cv2.imencode(".png", (skdata.camera()[:64, :64].astype(np.uint16) * 257))
    assert ok and ok16
    assert png_gray8_pixels(colour.tobytes(), "image") is None
    assert png_gray8_pixels(deep.tobytes(), "image") is None
    rows = np.zeros((8, 9), np.uint8).tobytes()
    with_trns = _png_of_rows(8, rows, 8, extra=_chunk(b"tRNS", b"\x00\x00"))
    assert png_gray8_pixels(with_trns, "image") is None
    info = check_image(colour.tobytes(), "image", 10**8)
    np.testing.assert_array_equal(decode_gray(colour.tobytes(), info, "image"), _opencv(colour))


def test_an_unknown_filter_type_is_refused_naming_the_row():
    rows = np.zeros((10, 1 + 16), np.uint8)
    rows[6, 0] = 5
    data = _png_of_rows(16, rows.tobytes(), 10)
    with pytest.raises(InvalidInputError, match="row 6"):
        png_gray8_pixels(data, "image")
    with pytest.raises(InvalidInputError):
        decode_gray(data, check_image(data, "image", 10**8), "image")


def test_a_short_or_bombed_stream_is_still_refused_before_unfiltering():
    rows = np.zeros((10, 1 + 16), np.uint8).tobytes()
    with pytest.raises(InvalidInputError, match="ends after"):
        png_gray8_pixels(_png_of_rows(16, rows[:-17], 10), "image")
    with pytest.raises(InvalidInputError, match="inflates beyond"):
        png_gray8_pixels(_png_of_rows(16, rows + rows, 10), "image")

"""Encoded images (PNG, JPEG): what the header declares, and decoding work bounded by it.

:func:`read_image_header` reads the format, size, bit depth and colour type from the PNG
IHDR chunk or the JPEG SOF segment, without decoding anything.

Bounding the decoding work:

A PNG's header can declare a camera-sized image while its compressed data inflates to
gigabytes: libpng inflates the whole zlib stream (to find its end) and its compressed
ancillary chunks, so a 4 MB upload can cost many seconds of CPU. A progressive JPEG can
repeat scans over the same pixels without limit. Before OpenCV sees the bytes:

* PNG: walk the chunks, inflate the IDAT stream with an output cap of exactly the
  filtered size that the header's width, height, bit depth, colour type and interlacing
  need, and refuse a stream that would inflate further, or ends short. OpenCV then gets a
  rebuilt file with only the critical chunks (IHDR, PLTE, tRNS, the image data, IEND): no
  ancillary chunk (zTXt, iCCP, ...) is ever inflated, and the image data is the stream
  already inflated here, in stored deflate blocks, so it is not inflated twice.
* JPEG: count the scans (SOS markers; entropy-coded data stuffs every 0xFF byte, so the
  marker cannot occur inside it) and refuse more than a real progressive file uses.

So a hostile image costs at most about what a real image of its declared size costs.
:func:`png_gray8_pixels` decodes the common mono camera PNG itself from the stream
inflated here. Pure bytes in, bytes (or pixels) out; errors are ``InvalidInputError`` (HTTP 422).
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from typing import Literal

import numpy as np

from monoloc.core.errors import InvalidInputError

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_SOI = b"\xff\xd8\xff"
# Samples per pixel by PNG colour type, and the bit depths each allows (PNG spec 11.2.2).
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}
_PNG_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}
# Adam7 passes: (x0, y0, dx, dy).
_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2))
_ADAM7 += ((0, 1, 1, 2),)
_KEPT_CHUNKS = (b"PLTE", b"tRNS")
# JPEG start-of-frame markers carrying the image size (C4, C8 and CC are not frames).
_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
# libjpeg's own progressive files use about 10 scans; a 3-channel file with every
# spectral band and successive-approximation bit split stays far below this.
MAX_JPEG_SCANS = 100


@dataclass(frozen=True)
class ImageInfo:
    """What the header of an encoded image says: format, size, PNG bit depth/colour type."""

    kind: Literal["png", "jpeg"]
    width_px: int
    height_px: int
    bit_depth: int = 8
    png_color_type: int | None = None


def _png_header(data: bytes, what: str) -> ImageInfo:
    # Signature (8), then the IHDR chunk: length (4), b"IHDR", width, height, depth, colour.
    if len(data) < 33 or data[12:16] != b"IHDR":
        raise InvalidInputError(f"{what}: PNG header is truncated or has no IHDR chunk")
    width, height, depth, color = struct.unpack(">IIBB", data[16:26])
    return ImageInfo("png", width, height, depth, color)


def _jpeg_header(data: bytes, what: str) -> ImageInfo:
    pos = 2
    while pos + 4 <= len(data):
        if data[pos] != 0xFF:
            raise InvalidInputError(f"{what}: JPEG marker expected at byte {pos}")
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length
            pos += 2
            continue
        if marker in (0xD9, 0xDA):
            break  # end of image / start of scan before any frame header
        (length,) = struct.unpack(">H", data[pos + 2 : pos + 4])
        if length < 2:
            raise InvalidInputError(f"{what}: JPEG segment at byte {pos} has length {length}")
        if marker in _SOF_MARKERS:
            if pos + 9 > len(data):
                break
            depth, height, width = struct.unpack(">BHH", data[pos + 4 : pos + 9])
            return ImageInfo("jpeg", width, height, depth)
        pos += 2 + length
    raise InvalidInputError(f"{what}: JPEG has no frame header (SOF) giving its size")


def read_image_header(data: bytes, what: str) -> ImageInfo:
    """Format and size of a PNG or JPEG from its header; InvalidInputError otherwise."""
    if data.startswith(PNG_SIGNATURE):
        return _png_header(data, what)
    if data.startswith(JPEG_SOI):
        return _jpeg_header(data, what)
    raise InvalidInputError(f"{what} is not a valid PNG/JPEG image (first bytes {data[:8]!r})")


def png_filtered_size(
    width_px: int, height_px: int, bit_depth: int, color_type: int, interlaced: bool
) -> int:
    """Bytes of the filtered image data (one filter byte per row) the header implies."""
    bits_per_pixel = _PNG_CHANNELS[color_type] * bit_depth

    def rows(width: int, height: int) -> int:
        return height * (1 + (width * bits_per_pixel + 7) // 8) if width and height else 0

    if not interlaced:
        return rows(width_px, height_px)
    return sum(
        rows(max(0, (width_px - x0 + dx - 1) // dx), max(0, (height_px - y0 + dy - 1) // dy))
        for x0, y0, dx, dy in _ADAM7
    )


def _chunk(kind: bytes, payload: bytes) -> bytes:
    crc = zlib.crc32(payload, zlib.crc32(kind))
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", crc)


def _png_chunks(data: bytes, what: str) -> tuple[bytes, dict[bytes, bytes], list[bytes]]:
    """(IHDR payload, kept critical chunks, IDAT payloads) of a PNG, up to IEND."""
    pos = len(PNG_SIGNATURE)
    ihdr, kept, idat = None, {}, []
    while True:
        if pos + 8 > len(data):
            raise InvalidInputError(f"{what}: PNG is truncated (no IEND chunk)")
        length, kind = struct.unpack(">I4s", data[pos : pos + 8])
        end = pos + 12 + length
        if end > len(data):
            raise InvalidInputError(f"{what}: PNG chunk {kind!r} at byte {pos} is truncated")
        payload = data[pos + 8 : pos + 8 + length]
        if kind == b"IHDR" and ihdr is None:
            ihdr = payload
        elif kind == b"IDAT":
            idat.append(payload)
        elif kind in _KEPT_CHUNKS:
            kept[kind] = payload
        elif kind == b"IEND":
            break
        pos = end
    if ihdr is None or len(ihdr) != 13:
        raise InvalidInputError(f"{what}: PNG has no valid IHDR chunk")
    if not idat:
        raise InvalidInputError(f"{what}: PNG has no image data (IDAT)")
    return ihdr, kept, idat


def _inflate_exactly(idat: list[bytes], expected: int, what: str) -> bytes:
    """The IDAT stream inflated (the filtered scanlines), after checking that it inflates
    to exactly ``expected`` bytes; never inflates more than expected + 1."""
    inflater = zlib.decompressobj()
    try:
        # one call on the joined chunks: a call per IDAT chunk (a camera frame has ~40)
        # regrows the output each time, 2.7x the inflate time of a noisy frame
        out = inflater.decompress(b"".join(idat), expected + 1)
    except zlib.error as exc:
        raise InvalidInputError(f"{what}: PNG image data is corrupt ({exc})") from exc
    if len(out) > expected:
        raise InvalidInputError(
            f"{what}: PNG data inflates beyond the {expected} bytes its header needs"
        )
    if not inflater.eof or len(out) != expected:
        produced = len(out)
        raise InvalidInputError(
            f"{what}: PNG image data ends after {produced} of the {expected} bytes its header needs"
        )
    return out


def _checked_png(data: bytes, what: str) -> tuple[bytes, dict[bytes, bytes], bytes]:
    """(IHDR payload, kept critical chunks, the inflated filtered scanlines) of a PNG
    whose header is valid and whose image data inflates to exactly the declared size."""
    if not data.startswith(PNG_SIGNATURE):
        raise InvalidInputError(f"{what}: not a PNG")
    ihdr, kept, idat = _png_chunks(data, what)
    width, height, depth, color, compression, filtering, interlace = struct.unpack(">IIBBBBB", ihdr)
    if width == 0 or height == 0:
        raise InvalidInputError(f"{what}: PNG header says {width}x{height} pixels")
    if depth not in _PNG_DEPTHS.get(color, ()) or compression or filtering or interlace > 1:
        raise InvalidInputError(
            f"{what}: invalid PNG header (bit depth {depth}, colour type {color}, "
            f"compression {compression}, filter {filtering}, interlace {interlace})"
        )
    expected = png_filtered_size(width, height, depth, color, bool(interlace))
    return ihdr, kept, _inflate_exactly(idat, expected, what)


def bounded_png(data: bytes, what: str) -> bytes:
    """A PNG whose decoding costs what its header declares: the critical chunks only,
    with the image data checked to inflate to exactly the declared size."""
    ihdr, kept, filtered = _checked_png(data, what)
    # Inflated once here; the decoder gets the scanlines in stored (level 0) deflate
    # blocks, which it copies instead of inflating them a second time (a camera frame:
    # 6.2 instead of 9.0 ms to decode, identical pixels).
    stream = zlib.compress(filtered, 0)
    parts = [PNG_SIGNATURE, _chunk(b"IHDR", ihdr)]
    parts += [_chunk(kind, kept[kind]) for kind in _KEPT_CHUNKS if kind in kept]
    parts += [_chunk(b"IDAT", stream), _chunk(b"IEND", b"")]
    return b"".join(parts)


def png_gray8_pixels(data: bytes, what: str) -> np.ndarray | None:
    """(H, W) uint8 of an 8-bit grayscale, non-interlaced PNG without PLTE or tRNS (a
    mono camera's frame), unfiltered here from the stream inflated once to bound it: no
    rebuilt file and no second pass by libpng (a noisy 1241 x 376 frame: about half the
    time of ``bounded_png`` + ``cv2.imdecode``, identical pixels). None for any other
    PNG, which the decoder gets through :func:`bounded_png`."""
    if len(data) < 33 or data[24:26] != b"\x08\x00" or data[28] != 0:
        return None  # header bytes: bit depth 8, colour type 0, interlace 0
    ihdr, kept, filtered = _checked_png(data, what)
    width, height, depth, color, _, _, interlace = struct.unpack(">IIBBBBB", ihdr)
    if kept or (depth, color, interlace) != (8, 0, 0):
        return None
    from monoloc.server._png_kernel import unfilter_rows

    pixels = np.empty((height, width), dtype=np.uint8)
    bad_row = unfilter_rows(np.frombuffer(filtered, dtype=np.uint8), height, width, 1, pixels)
    if bad_row >= 0:
        raise InvalidInputError(f"{what}: PNG row {bad_row} has an unknown filter type")
    return pixels


def check_jpeg_scans(data: bytes, what: str) -> None:
    """Refuse a JPEG with more than MAX_JPEG_SCANS scans (each one a pass over the image)."""
    scans = data.count(b"\xff\xda")
    if scans > MAX_JPEG_SCANS:
        raise InvalidInputError(
            f"{what}: JPEG has {scans} scans; at most {MAX_JPEG_SCANS} are accepted"
        )


def bounded_for_decoding(data: bytes, what: str) -> bytes:
    """The bytes to hand to the decoder: a bounded PNG, or the JPEG after its scan check.
    Anything else is returned as it is (the decoder refuses it)."""
    if data.startswith(PNG_SIGNATURE):
        return bounded_png(data, what)
    if data.startswith(JPEG_SOI):
        check_jpeg_scans(data, what)
    return data

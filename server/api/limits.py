"""Request limits: body size while receiving, image type and pixel count before decoding.

* :class:`BodySizeLimitMiddleware` (pure ASGI) answers 413 at once when a declared
  ``Content-Length`` exceeds the limit, and counts the bytes of every body as they
  arrive (chunked bodies too), failing the request with 413 as soon as the count passes
  the limit: a client cannot make the server buffer more than the limit.
* :func:`check_image` accepts only PNG and JPEG, by magic bytes (415), and reads the
  width and height from the PNG IHDR chunk or the JPEG SOF segment before anything is
  decoded: too many pixels -> 413, a broken header -> 422.
  An image narrower or lower than ``MIN_IMAGE_SIDE_PX`` is refused (422): ORB cannot place
  a single keypoint inside its border.
* :func:`decode_gray` / :func:`decode_depth_png` decode (call them off the event loop),
  after :mod:`monoloc.server.encoded_image` has bounded the decoding work to the declared
  size (a compression bomb is refused with 422 before OpenCV sees it).
"""

from __future__ import annotations

import json
from typing import Literal

import numpy as np
from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from monoloc.core.errors import InvalidInputError
from monoloc.server.api.errors import PayloadTooLargeError, UnsupportedMediaTypeError, error_body
from monoloc.server.encoded_image import (
    JPEG_SOI,
    PNG_SIGNATURE,
    ImageInfo,
    bounded_for_decoding,
    png_gray8_pixels,
    read_image_header,
)

# ORB's default border (edge threshold 31 px on each side) leaves no room for a keypoint in
# a smaller image.
MIN_IMAGE_SIDE_PX = 63


class BodyTooLargeError(HTTPException):
    """Raised from ``receive`` when the body passes the limit. An HTTPException so that
    FastAPI's body parsing lets it through to the JSON error handler unchanged."""

    def __init__(self, limit: int, which: str = "MONOLOC_MAX_BODY_BYTES") -> None:
        super().__init__(413, f"request body exceeds the limit of {limit} bytes ({which})")


class BodySizeLimitMiddleware:
    """Refuse HTTP bodies larger than ``max_body_bytes`` while they are received."""

    def __init__(self, app: ASGIApp, max_body_bytes: int) -> None:
        self.app = app
        self.max_body_bytes = max_body_bytes

    async def _refuse(self, send: Send) -> None:
        message = f"request body exceeds the limit of {self.max_body_bytes} bytes"
        body = json.dumps(error_body("payload_too_large", message)).encode()
        headers = [
            (b"content-type", b"application/json"),
            (b"content-length", str(len(body)).encode()),
            (b"connection", b"close"),
        ]
        await send({"type": "http.response.start", "status": 413, "headers": headers})
        await send({"type": "http.response.body", "body": body})

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        for name, value in scope.get("headers", ()):
            if name == b"content-length":
                try:
                    declared = int(value)
                except ValueError:
                    declared = -1
                if declared > self.max_body_bytes:
                    await self._refuse(send)
                    return
        received = 0
        started = False

        async def counting_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_body_bytes:
                    raise BodyTooLargeError(self.max_body_bytes)
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, counting_receive, tracking_send)
        except BodyTooLargeError:
            if started:
                raise
            await self._refuse(send)


def sniff_image(data: bytes, what: str) -> Literal["png", "jpeg"]:
    """'png' or 'jpeg' from the magic bytes; UnsupportedMediaTypeError otherwise."""
    if data.startswith(PNG_SIGNATURE):
        return "png"
    if data.startswith(JPEG_SOI):
        return "jpeg"
    raise UnsupportedMediaTypeError(
        f"{what} is not a PNG or JPEG image (first bytes {data[:8]!r}); only PNG and JPEG "
        "are accepted"
    )


def check_image(data: bytes, what: str, max_pixels: int) -> ImageInfo:
    """Type (415) and size (413, 422) of an encoded image, from its header only."""
    sniff_image(data, what)
    info = read_image_header(data, what)
    if info.width_px <= 0 or info.height_px <= 0:
        raise InvalidInputError(f"{what}: header says {info.width_px}x{info.height_px} pixels")
    if min(info.width_px, info.height_px) < MIN_IMAGE_SIDE_PX:
        raise InvalidInputError(
            f"{what} is {info.width_px}x{info.height_px} pixels; both sides must be at least "
            f"{MIN_IMAGE_SIDE_PX} px"
        )
    if info.width_px * info.height_px > max_pixels:
        raise PayloadTooLargeError(
            f"{what} is {info.width_px}x{info.height_px} = {info.width_px * info.height_px} "
            f"pixels; the limit is {max_pixels}"
        )
    return info


def decode_gray(data: bytes, info: ImageInfo, what: str) -> np.ndarray:
    """Decode a checked image to (H, W) uint8 grayscale; 422 if it does not decode to the
    size its header announced."""
    import cv2

    image = png_gray8_pixels(data, what) if info.kind == "png" else None
    if image is None:
        data = bounded_for_decoding(data, what)
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
    if image is None or image.shape != (info.height_px, info.width_px):
        raise InvalidInputError(f"{what}: the {info.kind.upper()} data cannot be decoded")
    return image


def decode_depth_png(data: bytes, info: ImageInfo, what: str) -> np.ndarray:
    """Decode a checked 16-bit single-channel PNG to (H, W) uint16 raw depth units."""
    import cv2

    if info.kind != "png" or info.bit_depth != 16 or info.png_color_type != 0:
        raise InvalidInputError(
            f"{what} must be a 16-bit grayscale PNG (got {info.kind}, depth {info.bit_depth}, "
            f"PNG colour type {info.png_color_type})"
        )
    data = bounded_for_decoding(data, what)
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None or image.dtype != np.uint16 or image.shape != (info.height_px, info.width_px):
        raise InvalidInputError(f"{what}: the PNG data cannot be decoded as 16-bit depth")
    return image

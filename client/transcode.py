"""Frames re-encoded on the vehicle before they are sent: JPEG instead of the recording's
PNG (a quarter to a seventh of the bytes, and about a quarter of the server's decode time
for a camera frame; bench/frame_cost.py gives both with the accuracy beside PNG).

Pillow encodes (the ``bags`` extra installs it; the vehicle library stays free of
OpenCV). A frame is encoded as it was recorded in grayscale (mode L) or colour (RGB);
the server turns it to grayscale either way.
"""

from __future__ import annotations

import dataclasses
import io
from collections.abc import Callable
from pathlib import Path

from monoloc.client.replay import ReplayRun
from monoloc.core.errors import InvalidInputError

IMAGE_FORMATS = ("recorded", "jpeg")


def jpeg_encoder(quality: int) -> Callable[[bytes], bytes]:
    """A function from an encoded PNG/JPEG frame to a baseline JPEG of ``quality`` (1-95,
    Pillow's useful range); InvalidInputError when Pillow is missing or the quality is
    out of range."""
    if not 1 <= quality <= 95:
        raise InvalidInputError(f"JPEG quality must be within 1-95, got {quality}")
    try:
        from PIL import Image
    except ModuleNotFoundError:
        raise InvalidInputError("sending JPEG needs Pillow: pip install 'monoloc[bags]'") from None

    def encode(data: bytes) -> bytes:
        try:
            with Image.open(io.BytesIO(data)) as image:
                image.load()
                frame = image if image.mode in ("L", "RGB") else image.convert("RGB")
        except OSError as exc:
            raise InvalidInputError(f"a frame cannot be read to re-encode it: {exc}") from exc
        out = io.BytesIO()
        frame.save(out, format="JPEG", quality=quality)
        return out.getvalue()

    return encode


def with_image_format(run: ReplayRun, image_format: str, jpeg_quality: int = 90) -> ReplayRun:
    """``run`` whose frames are sent as ``image_format``: "recorded" (the files' own
    bytes) or "jpeg" (re-encoded at ``jpeg_quality``)."""
    if image_format not in IMAGE_FORMATS:
        raise InvalidInputError(
            f"image format must be one of {', '.join(IMAGE_FORMATS)}, got {image_format!r}"
        )
    if image_format == "recorded":
        return run
    encode = jpeg_encoder(jpeg_quality)
    read = run.read_image

    def read_as_jpeg(path: Path) -> bytes:
        return encode(path.read_bytes() if read is None else read(path))

    note = f"frames sent as JPEG quality {jpeg_quality} (re-encoded on the vehicle)"
    return dataclasses.replace(run, read_image=read_as_jpeg, notes=[*run.notes, note])

"""PNG files: an image's size from its header, without decoding it (decoding needs OpenCV,
which the light packages do not import)."""

from __future__ import annotations

import os

from monoloc.core.errors import InputFileError

SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of a PNG read from its header; InputFileError naming the file if
    it is not a PNG or cannot be read."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(24)
    except OSError as exc:
        raise InputFileError(path, f"cannot read image: {exc.strerror or exc}") from exc
    if len(head) < 24 or head[:8] != SIGNATURE or head[12:16] != b"IHDR":
        raise InputFileError(path, "not a PNG image")
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if width <= 0 or height <= 0:
        raise InputFileError(path, f"PNG header gives an empty image ({width}x{height})")
    return width, height

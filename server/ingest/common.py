"""What the ingestion's sources share: frame ranges, the loaded-frame record the pipeline
consumes, image identity and decoding. The sources themselves are ``sources``; the
formats' files are read in ``monoloc.core.formats`` (their errors, ``InputFileError``,
name the file and line).
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.server.encoded_image import bounded_for_decoding

_RANGE_RE = re.compile(r"^\s*(-?\d*)\s*:\s*(-?\d*)\s*(?::\s*(-?\d*)\s*)?$")


def parse_frame_range(text: str | None) -> slice | None:
    """``"A:B"`` (or ``"A:"``, ``":B"``, ``"A:B:S"``) -> slice(A, B, S), Python semantics.

    Frames are numbered from 0 as in the file names; ``0:3860`` selects frames 0..3859,
    ``3860:`` the rest (the paper's 85 % / 15 % split of KITTI 00); negative bounds count
    from the end. None or an empty string selects everything.
    """
    if text is None or not text.strip():
        return None
    match = _RANGE_RE.match(text)
    if match is None:
        raise InvalidInputError(f"invalid frame range {text!r}: expected A:B, A:, :B or A:B:S")
    start, stop, step = (int(g) if g not in (None, "") else None for g in match.groups())
    if step == 0:
        raise InvalidInputError(f"invalid frame range {text!r}: step must not be 0")
    return slice(start, stop, step)


@dataclass(frozen=True)
class LoadedFrame:
    """One frame read from disk: the image file's bytes, the
    decoded (H, W) uint8 grayscale image and the frame's 3D source (a ``LidarSource`` or
    ``DepthSource`` of ``monoloc.server.entry_builder``)."""

    image_bytes: bytes
    image_gray: np.ndarray
    source: object


CONTENT_HASH_DOMAIN = b"monoloc/gray-u8/v1"


def content_hash(image_gray: np.ndarray) -> str:
    """sha256 (64 hex) of a decoded (H, W) uint8 image: its size and pixels, under a domain
    tag so that it never equals the sha256 of a file's bytes.

    Entries are identified by what they were built from, the decoded grayscale image, not
    by the file's bytes: the same picture re-encoded, or with bytes appended after its
    end, is the same entry. Entries stored before this rule carry the sha256 of their
    file's bytes (``bytes_hash``); duplicate checks look both up.
    """
    image = np.ascontiguousarray(image_gray, dtype=np.uint8)
    if image.ndim != 2:
        raise InvalidInputError(f"content_hash needs an (H, W) image, got shape {image.shape}")
    digest = hashlib.sha256(CONTENT_HASH_DOMAIN)
    digest.update(np.array(image.shape, dtype="<u8").tobytes())
    digest.update(image.data)
    return digest.hexdigest()


def bytes_hash(data: bytes) -> str:
    """sha256 (64 hex) of a file's bytes: the identity of entries stored before
    ``content_hash`` (still looked up so that old maps keep refusing their duplicates)."""
    return hashlib.sha256(data).hexdigest()


def read_bytes(path: Path, what: str = "file") -> bytes:
    """The file's bytes; InputFileError naming it if it cannot be read or is empty."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise InputFileError(path, f"cannot read {what}: {exc.strerror or exc}") from exc
    if not data:
        raise InputFileError(path, f"{what} is empty")
    return data


def _bounded(data: bytes, path: Path, what: str = "image") -> bytes:
    """The bytes with their decoding work bounded to the declared size (encoded_image)."""
    try:
        return bounded_for_decoding(data, path.name)
    except InvalidInputError as exc:
        detail = str(exc).removeprefix(f"{path.name}: ")
        raise InputFileError(path, f"unreadable {what} ({detail})") from exc


def decode_gray(data: bytes, path: Path) -> np.ndarray:
    """Decode PNG/JPEG bytes to (H, W) uint8 grayscale (colour is converted with OpenCV's
    luma weights); InputFileError naming ``path`` if the bytes are not a readable image."""
    import cv2

    buffer = np.frombuffer(_bounded(data, path), dtype=np.uint8)
    image = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED)
    if image is None or image.size == 0:
        raise InputFileError(path, "unreadable image (not a valid PNG/JPEG)")
    if image.dtype != np.uint8:
        if image.dtype != np.uint16:
            raise InputFileError(path, f"unsupported image sample type {image.dtype}")
        image = (image >> 8).astype(np.uint8)  # 16-bit intensity image: keep the top byte
    if image.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        image = cv2.cvtColor(image, code)
    return np.ascontiguousarray(image)


def decode_depth(data: bytes, path: Path) -> np.ndarray:
    """Decode a 16-bit single-channel depth PNG to (H, W) uint16 (raw units)."""
    import cv2

    image = cv2.imdecode(
        np.frombuffer(_bounded(data, path, "depth image"), dtype=np.uint8), cv2.IMREAD_UNCHANGED
    )
    if image is None or image.size == 0:
        raise InputFileError(path, "unreadable depth image (not a valid PNG)")
    if image.ndim != 2 or image.dtype != np.uint16:
        raise InputFileError(
            path, f"depth image must be 16-bit single-channel, got {image.dtype} {image.shape}"
        )
    return image

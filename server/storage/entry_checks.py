"""Validation of what goes into an entry row (shapes, dtypes, finiteness, consistency)."""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from typing import Any

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import check_rigid, planar_from_T_world_from_cam
from monoloc.server.storage import arrays as arr
from monoloc.server.storage.records import Area, NewEntry

SHA256_HEX_RE = re.compile(r"^[0-9a-f]{64}$")
TAG_RE = re.compile(r"^[a-z0-9][a-z0-9_.:-]{0,63}$")


def check_source_hash(source_image_hash: str) -> str:
    """A sha256 hex digest, lower-cased; InvalidInputError otherwise."""
    value = str(source_image_hash).strip().lower()
    if not SHA256_HEX_RE.match(value):
        raise InvalidInputError(
            f"source_image_hash must be 64 hex characters (sha256), got {source_image_hash!r}"
        )
    return value


def normalise_tag(tag: str, what: str = "tag") -> str:
    """One tag lower-cased and stripped (``Night `` -> ``night``); InvalidInputError naming
    ``what`` (e.g. "condition") if it breaks the tag rule."""
    value = str(tag).strip().lower()
    if not TAG_RE.match(value):
        raise InvalidInputError(
            f"invalid {what} {tag!r}: 1-64 of a-z, 0-9, '_', '.', ':', '-', "
            "starting with a letter or digit"
        )
    return value


def normalise_tags(tags: Iterable[str]) -> list[str]:
    """Lower-cased, stripped, de-duplicated, sorted tags such as ``night``, ``off-center``."""
    if isinstance(tags, str):
        raise InvalidInputError(f"tags must be a list of strings, got the string {tags!r}")
    return sorted({normalise_tag(tag) for tag in tags})


def check_area(area: Area) -> tuple[float, float, float]:
    x, y, r = float(area.x_m), float(area.y_m), float(area.radius_m)
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(r)) or r < 0:
        raise InvalidInputError(f"invalid area filter {area}: need finite x, y and radius >= 0")
    return x, y, r


def check_code_and_vlad(vlad: np.ndarray, code: np.ndarray, where: str) -> tuple[bytes, bytes]:
    """Blobs of a (2048,) float32 VLAD and its (256,) uint8 binary code."""
    return (
        arr.pack_array(vlad, arr.VLAD, f"{where}: vlad"),
        arr.pack_array(code, arr.CODE, f"{where}: code"),
    )


def check_new_entry(entry: NewEntry, source_hash: str) -> dict[str, Any]:
    """Column values of a new entry row (blobs packed, planar pose derived from the pose).

    Checks: T_world_from_cam rigid; keypoints, descriptors and points share N >= 1;
    points in front of the camera (z > 0); keypoints inside the image (1 px slack).
    """
    where = f"entry {source_hash[:12]}"
    T = check_rigid(entry.T_world_from_cam, f"{where}: T_world_from_cam")
    x_m, y_m, yaw_rad = (float(v) for v in planar_from_T_world_from_cam(T))
    width, height = int(entry.image_width_px), int(entry.image_height_px)
    if width <= 0 or height <= 0:
        raise InvalidInputError(f"{where}: invalid image size {width}x{height}")
    vlad_blob, code_blob = check_code_and_vlad(entry.vlad, entry.code, where)
    keypoints = np.asarray(entry.keypoints_px)
    kp_blob = arr.pack_array(keypoints, arr.KEYPOINTS, f"{where}: keypoints_px")
    desc_blob = arr.pack_array(entry.descriptors, arr.DESCRIPTORS, f"{where}: descriptors")
    points = np.asarray(entry.points_cam)
    pts_blob = arr.pack_array(points, arr.POINTS, f"{where}: points_cam")
    counts = {len(keypoints), len(np.asarray(entry.descriptors)), len(points)}
    if len(counts) != 1:
        raise InvalidInputError(
            f"{where}: keypoints_px, descriptors and points_cam must have the same N, "
            f"got {len(keypoints)}, {len(np.asarray(entry.descriptors))}, {len(points)}"
        )
    n_points = counts.pop()
    if n_points == 0:
        raise InvalidInputError(f"{where}: no keypoints with 3D points")
    if np.any(points[:, 2] <= 0):
        bad = int(np.argmax(points[:, 2] <= 0))
        raise InvalidInputError(f"{where}: points_cam[{bad}] is not in front of the camera")
    outside = (
        (keypoints[:, 0] < -1.0)
        | (keypoints[:, 0] > width)
        | (keypoints[:, 1] < -1.0)
        | (keypoints[:, 1] > height)
    )
    if np.any(outside):
        bad = int(np.argmax(outside))
        raise InvalidInputError(
            f"{where}: keypoints_px[{bad}] = {keypoints[bad].tolist()} is outside the "
            f"{width}x{height} image"
        )
    ts = entry.timestamp_s
    if ts is not None and not math.isfinite(float(ts)):
        raise InvalidInputError(f"{where}: timestamp_s must be finite, got {ts}")
    return {
        "source_image_hash": source_hash,
        "T_world_from_cam": arr.pack_array(T, arr.POSE, f"{where}: T_world_from_cam"),
        "x_m": x_m,
        "y_m": y_m,
        "yaw_rad": yaw_rad,
        "vlad": vlad_blob,
        "code": code_blob,
        "keypoints_px": kp_blob,
        "descriptors": desc_blob,
        "points_cam": pts_blob,
        "n_points": n_points,
        "image_width_px": width,
        "image_height_px": height,
        "timestamp_s": None if ts is None else float(ts),
    }

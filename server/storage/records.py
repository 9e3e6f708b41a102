"""Plain frozen records the repositories return (no ORM objects leak out of a session),
and the input record of a new map entry.

A record whose row holds it as it is (a run, a job) is a pydantic model read from the
row's attributes (``RunRecord.model_validate(row)``); the others are dataclasses their
repository builds (arrays decoded from blobs, tags, the map's camera). Arrays in records
are numpy arrays; those decoded from blobs are read-only views.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict

from monoloc.core.camera import CameraIntrinsics

_FROM_ROW = ConfigDict(frozen=True, from_attributes=True)

# Reading what a map looks like needs a valid key of any scope (see ApiKeyRecord.has_scope).
READ_ACCESS = "read"


@dataclass(frozen=True)
class VocabularyRecord:
    """A visual vocabulary: ``centres`` (64, 32) float32 in ORB byte space."""

    id: int
    version_hash: str
    n_words: int
    description: str
    created_at: datetime
    centres: np.ndarray = field(repr=False)


@dataclass(frozen=True)
class MapChangeRecord:
    """One step of a map's change log: ``kind`` (add, delete, retag, vlad, vocabulary)
    took the map to ``version``; ``entry_id`` is the entry concerned, if any."""

    map_id: int
    version: int
    kind: str
    entry_id: int | None


@dataclass(frozen=True)
class MapRecord:
    """A map with its camera, vocabulary, version counter and entry count."""

    id: int
    name: str
    camera: CameraIntrinsics
    vocabulary_id: int
    vocabulary_hash: str
    version: int
    calibration: dict[str, Any] | None
    n_entries: int
    created_at: datetime
    updated_at: datetime
    # monoloc/core/geo.py GeoReference.to_dict(), or None: the map is not geo-referenced
    geo_reference: dict[str, Any] | None = None
    # how the map's entries picked their ORB corners (vision.features.selection_rule)
    features: dict[str, Any] | None = None


class RunRecord(BaseModel):
    """One ingested recording (mapping run) and its counters."""

    model_config = _FROM_ROW
    id: int
    map_id: int
    kind: str
    source_format: str
    source_name: str
    status: str
    frames_total: int
    frames_done: int
    entries_added: int
    frames_skipped: int
    skip_reasons: dict[str, int]
    error: str | None
    created_at: datetime
    updated_at: datetime
    registration: dict | None = None  # how the run was registered to the map, if it was


@dataclass(frozen=True)
class EntrySummary:
    """A map entry without its arrays: planar pose (x_m, y_m, yaw_rad) in the z-up world."""

    id: int
    map_id: int
    run_id: int | None
    source_image_hash: str
    x_m: float
    y_m: float
    yaw_rad: float
    tags: tuple[str, ...]
    vocabulary_id: int
    n_points: int
    image_width_px: int
    image_height_px: int
    timestamp_s: float | None
    created_at: datetime


@dataclass(frozen=True)
class EntryData:
    """A map entry with its arrays, as localization needs them.

    T_world_from_cam (4, 4) float64; vlad (2048,) float32; code (256,) uint8;
    keypoints_px (N, 2) float32; descriptors (N, 32) uint8; points_cam (N, 3) float32
    in the entry's camera frame (OpenCV).
    """

    summary: EntrySummary
    T_world_from_cam: np.ndarray = field(repr=False)
    vlad: np.ndarray = field(repr=False)
    code: np.ndarray = field(repr=False)
    keypoints_px: np.ndarray = field(repr=False)
    descriptors: np.ndarray = field(repr=False)
    points_cam: np.ndarray = field(repr=False)

    @property
    def id(self) -> int:
        return self.summary.id


@dataclass(frozen=True)
class EntryImageData:
    """A small grey JPEG of an entry's reference image (``width_px`` x ``height_px``, the
    JPEG's own size) and the keypoints (M, 2) float32 in full-size image pixels that got
    no 3D point (the entry keeps only the others). For people, not for localization."""

    jpeg: bytes = field(repr=False)
    width_px: int
    height_px: int
    keypoints_without_point_px: np.ndarray = field(repr=False)


@dataclass(frozen=True)
class NewEntry:
    """What ingestion or the API hands to ``entries.add_entry``. Shapes as in EntryData.

    ``source_image_hash`` is the sha256 hex of the source image file (re-ingesting the
    same image into the same map is a no-op). ``vocabulary_id`` None means the map's
    current vocabulary (the one the VLAD must have been computed with).
    """

    source_image_hash: str
    T_world_from_cam: np.ndarray
    vlad: np.ndarray
    code: np.ndarray
    keypoints_px: np.ndarray
    descriptors: np.ndarray
    points_cam: np.ndarray
    image_width_px: int
    image_height_px: int
    tags: tuple[str, ...] = ()
    timestamp_s: float | None = None
    vocabulary_id: int | None = None
    image: EntryImageData | None = None  # stored beside the entry when given


@dataclass(frozen=True)
class Area:
    """A disc on the ground plane: centre (x_m, y_m) in the z-up world, radius in metres."""

    x_m: float
    y_m: float
    radius_m: float


@dataclass(frozen=True)
class MapVectors:
    """One batch of a map's retrieval data, rows aligned.

    entry_ids (B,) int64; vlads (B, 2048) float32; codes (B, 256) uint8;
    planar (B, 3) float64 rows of (x_m, y_m, yaw_rad).
    """

    entry_ids: np.ndarray
    vlads: np.ndarray
    codes: np.ndarray
    planar: np.ndarray


class JobRecord(BaseModel):
    """A durable long-running job (ingestion, vocabulary change, ...); ``params`` is the
    JSON of its kind's parameters (``monoloc.server.jobs.params``)."""

    model_config = _FROM_ROW
    id: int
    kind: str
    map_id: int | None
    run_id: int | None
    state: str
    progress: float
    message: str
    error: str | None
    params: dict[str, Any]
    result: dict[str, Any] | None
    created_at: datetime
    updated_at: datetime
    finished_at: datetime | None


@dataclass(frozen=True)
class ApiKeyRecord:
    """An API key as stored (never the key itself). ``admin`` implies every scope."""

    id: int
    name: str
    prefix: str
    scopes: frozenset[str]
    created_at: datetime
    revoked_at: datetime | None
    maps: frozenset[int] | None = None  # the maps it may touch; None: every map

    @property
    def revoked(self) -> bool:
        return self.revoked_at is not None

    def can_see_map(self, map_id: int) -> bool:
        """True if the key may read or act on map ``map_id`` (keys without maps: all)."""
        return self.maps is None or map_id in self.maps

    def has_scope(self, scope: str) -> bool:
        """True if the key grants ``scope`` (directly or through ``admin``). ``read`` (what
        the map looks like: maps, their calibration, geo reference, poses, coverage, live
        vehicles) is no scope of its own: every valid key has it."""
        if scope == READ_ACCESS:
            return bool(self.scopes)
        return scope in self.scopes or "admin" in self.scopes

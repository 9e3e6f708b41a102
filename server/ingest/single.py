"""Adding one reference image to a map: an encoded image, its pose and a 3D source
(a registered depth image, a LiDAR scan with extrinsics, or explicit per-keypoint points).

Also the small file readers the CLI's ``map add-image`` uses (pose text, LiDAR .bin,
depth PNG, extrinsics).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.geometry import check_rigid
from monoloc.server.encoded_image import read_image_header
from monoloc.server.entry_builder import BuildConfig, DepthSource, LidarSource, build_entry
from monoloc.server.ingest.common import (
    bytes_hash,
    content_hash,
    decode_depth,
    decode_gray,
    read_bytes,
)
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.records import EntrySummary
from monoloc.server.vision.features import orb_for_rule
from monoloc.server.vision.vocabulary import Vocabulary

UPLOAD = Path("<uploaded image>")


def add_single_image(
    session_factory: sessionmaker[Session],
    map_id: int,
    image_bytes: bytes,
    T_world_from_cam: np.ndarray,
    source: LidarSource | DepthSource | np.ndarray,
    *,
    tags: tuple[str, ...] = (),
    registry=None,
    intrinsics: CameraIntrinsics | None = None,
    timestamp_s: float | None = None,
    config: BuildConfig = BuildConfig(),
) -> tuple[EntrySummary, bool]:
    """Decode a PNG/JPEG, build its entry and add it to the map; returns (summary, created).

    ``T_world_from_cam`` (4, 4) in the z-up world; ``intrinsics`` default to the map's
    camera. Idempotent by the decoded image (``content_hash``): the same picture again,
    whatever its encoding or trailing bytes, returns the existing entry with created False
    (as does an entry stored earlier under the sha256 of these very bytes). Raises
    InvalidInputError (unreadable image, wrong size, too few 3D points) and NotFoundError
    (no such map).
    """
    if not image_bytes:
        raise InvalidInputError("the image is empty")
    T_world_from_cam = check_rigid(T_world_from_cam, "T_world_from_cam")
    with session_scope(session_factory) as session:
        record = maps_repo.get_map(session, map_id)
        vocab = maps_repo.get_vocabulary(session, record.vocabulary_id)
    camera = intrinsics or record.camera
    # described as the map's other entries (maps.features)
    config = replace(config, orb=orb_for_rule(record.features, config.orb))
    # The declared size is checked before decoding: a small file may declare a huge image.
    declared = read_image_header(image_bytes, "image")
    if (declared.width_px, declared.height_px) != (camera.width_px, camera.height_px):
        raise InvalidInputError(
            f"image is {declared.width_px}x{declared.height_px} pixels; the camera is "
            f"{camera.width_px}x{camera.height_px}"
        )
    image = decode_gray(image_bytes, UPLOAD)
    vocabulary = Vocabulary.from_centres(np.asarray(vocab.centres), vocab.description)
    entry = build_entry(
        image,
        content_hash(image),
        T_world_from_cam,
        source,
        camera,
        vocabulary,
        vocab.id,
        config,
        tags=tuple(tags),
        timestamp_s=timestamp_s,
    )
    with session_scope(session_factory) as session:
        summary, created = entries_repo.add_entry(
            session, map_id, entry, also_known_as=(bytes_hash(image_bytes),)
        )
    if created and registry is not None:
        registry.entries_added(map_id)
    return summary, created


def parse_numbers(text: str, what: str) -> np.ndarray:
    """Numbers separated by commas and/or whitespace -> float64 array."""
    fields = text.replace(",", " ").split()
    try:
        values = np.array([float(f) for f in fields], dtype=np.float64)
    except ValueError as exc:
        raise InvalidInputError(f"{what}: not a list of numbers ({exc})") from exc
    if not np.all(np.isfinite(values)):
        raise InvalidInputError(f"{what}: contains NaN or infinite values")
    return values


def transform_from_numbers(values: np.ndarray, what: str) -> np.ndarray:
    """12 (3x4) or 16 (4x4) row-major numbers -> checked rigid (4, 4) transform."""
    if values.size not in (12, 16):
        raise InvalidInputError(f"{what}: expected 12 (3x4) or 16 (4x4) numbers, got {values.size}")
    T = np.eye(4)
    T[: values.size // 4] = values.reshape(-1, 4)
    return check_rigid(T, what, tol=1e-3)


def read_pose_file(path: Path) -> np.ndarray:
    """A text file of 12 or 16 numbers (T_world_from_cam, z-up world) -> (4, 4)."""
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(path, f"cannot read pose file: {exc}") from exc
    try:
        return transform_from_numbers(parse_numbers(text, str(path)), str(path))
    except InvalidInputError as exc:
        raise InputFileError(path, str(exc).removeprefix(f"{path}: ")) from exc


def read_lidar_extrinsics(spec: str) -> np.ndarray:
    """T_cam_from_lidar from a KITTI calib.txt path (its Tr line) or 12/16 numbers."""
    path = Path(spec)
    if path.is_file():
        from monoloc.core.formats.kitti import read_calib_file

        return read_calib_file(path).T_cam0_from_lidar
    return transform_from_numbers(parse_numbers(spec, "LiDAR extrinsics"), "LiDAR extrinsics")


def depth_source_from_file(path: Path, scale_per_m: float) -> DepthSource:
    """A registered 16-bit depth PNG and its scale (raw units per metre, TUM: 5000)."""
    return DepthSource(decode_depth(read_bytes(path, "depth image"), Path(path)), scale_per_m)


def lidar_source_from_file(path: Path, T_cam_from_lidar: np.ndarray) -> LidarSource:
    """A KITTI .bin scan (float32 x, y, z, r) and T_cam_from_lidar (4, 4)."""
    from monoloc.core.formats.kitti import read_scan

    return LidarSource(read_scan(Path(path)), T_cam_from_lidar)

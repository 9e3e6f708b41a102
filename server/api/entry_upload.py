"""Turn the multipart fields of ``POST .../entries`` into a stored entry.

Checks before any decoding: the image is PNG/JPEG with an acceptable pixel count, the
depth image a 16-bit grayscale PNG, the LiDAR scan a whole number of 16-byte points
within ``max_lidar_points``; poses are 12 or 16 finite numbers forming a rigid
transform. Then ``monoloc.server.ingest.single.add_single_image`` builds and stores the entry
and feeds the live index (on the CPU pool).
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.core.formats.kitti import LIDAR_POINT_BYTES
from monoloc.server.api.convert import entry_detail
from monoloc.server.api.deps import AppState
from monoloc.server.api.errors import PayloadTooLargeError
from monoloc.server.api.limits import ImageInfo, check_image, decode_depth_png
from monoloc.server.api.schemas import EntryCreated
from monoloc.server.entry_builder import DepthSource, LidarSource
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage.db import session_scope


@dataclass(frozen=True)
class NewEntryForm:
    image: bytes
    T_world_from_cam: str
    depth: bytes | None = None
    depth_scale: float | None = None
    lidar: bytes | None = None
    T_cam_from_lidar: str | None = None
    tags: tuple[str, ...] = ()
    timestamp_s: float | None = None


def parse_transform(text: str, what: str) -> np.ndarray:
    """(4, 4) rigid transform from a JSON array (flat or nested) or comma/space-separated
    numbers, 12 (3x4) or 16 (4x4), row-major."""
    from monoloc.server.ingest.single import parse_numbers, transform_from_numbers

    stripped = text.strip()
    if stripped.startswith("["):
        try:
            values = np.asarray(json.loads(stripped), dtype=np.float64).ravel()
        except (ValueError, TypeError) as exc:
            raise InvalidInputError(f"{what}: not a JSON array of numbers ({exc})") from exc
        if not np.all(np.isfinite(values)):
            raise InvalidInputError(f"{what}: contains NaN or infinite values")
    else:
        values = parse_numbers(stripped, what)
    return transform_from_numbers(values, what)


def _lidar_points(data: bytes, max_points: int) -> np.ndarray:
    if len(data) == 0 or len(data) % LIDAR_POINT_BYTES:
        raise InvalidInputError(
            f"lidar: {len(data)} bytes is not a whole number of 16-byte points (x, y, z, r float32)"
        )
    n = len(data) // LIDAR_POINT_BYTES
    if n > max_points:
        raise PayloadTooLargeError(f"lidar: {n} points; the limit is {max_points}")
    points = np.frombuffer(data, dtype="<f4").reshape(n, 4)
    if not np.all(np.isfinite(points[:, :3])):
        raise InvalidInputError("lidar: the scan contains NaN or infinite coordinates")
    return points


def check_form(form: NewEntryForm, max_pixels: int) -> tuple[ImageInfo, ImageInfo | None]:
    """Cheap checks (headers, exclusive sources) before any decoding."""
    info = check_image(form.image, "image", max_pixels)
    has_depth, has_lidar = form.depth is not None, form.lidar is not None
    if has_depth == has_lidar:
        raise InvalidInputError(
            "send exactly one 3D source: 'depth' (+ depth_scale) or 'lidar' (+ T_cam_from_lidar)"
        )
    depth_info = None
    if form.depth is not None:
        if form.depth_scale is None or not np.isfinite(form.depth_scale) or form.depth_scale <= 0:
            raise InvalidInputError("depth needs a positive depth_scale (raw units per metre)")
        depth_info = check_image(form.depth, "depth", max_pixels)
        if (depth_info.width_px, depth_info.height_px) != (info.width_px, info.height_px):
            raise InvalidInputError(
                f"depth is {depth_info.width_px}x{depth_info.height_px}, the image "
                f"{info.width_px}x{info.height_px}"
            )
    elif not form.T_cam_from_lidar:
        raise InvalidInputError("lidar needs T_cam_from_lidar (16 numbers, row-major)")
    return info, depth_info


def _build_and_store(
    state: AppState, map_id: int, form: NewEntryForm, depth_info: ImageInfo | None
) -> EntryCreated:
    from monoloc.server.ingest.single import add_single_image

    T_world_from_cam = parse_transform(form.T_world_from_cam, "T_world_from_cam")
    if form.depth is not None:
        assert depth_info is not None and form.depth_scale is not None
        source: DepthSource | LidarSource = DepthSource(
            decode_depth_png(form.depth, depth_info, "depth"), float(form.depth_scale)
        )
    else:
        assert form.lidar is not None and form.T_cam_from_lidar is not None
        source = LidarSource(
            _lidar_points(form.lidar, state.settings.max_lidar_points),
            parse_transform(form.T_cam_from_lidar, "T_cam_from_lidar"),
        )
    summary, created = add_single_image(
        state.sessions,
        map_id,
        form.image,
        T_world_from_cam,
        source,
        tags=form.tags,
        registry=state.registry,
        timestamp_s=form.timestamp_s,
    )
    with session_scope(state.sessions) as session:
        version = maps_repo.get_map(session, map_id).version
        (stored,) = entries_repo.get_entry_data(session, [summary.id])
    return EntryCreated(
        entry=entry_detail(summary, np.asarray(stored.T_world_from_cam)),
        created=created,
        map_version=version,
    )


async def add_entry_from_form(state: AppState, map_id: int, form: NewEntryForm) -> EntryCreated:
    _, depth_info = check_form(form, state.settings.max_image_pixels)
    return await state.run_cpu(_build_and_store, state, map_id, form, depth_info)

"""Repository of vehicles' cameras: register, get, list, delete. Never commits.

A camera is registered once by a vehicle (its key is recorded) and then named by its id
in every query; it is never changed (delete and register again). A key limited to some
maps registers and sees cameras as any other key does: a camera belongs to no map (one
fleet camera is driven against every map of a city).
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from monoloc.core.camera import CameraIntrinsics, LensDistortion
from monoloc.core.errors import NotFoundError
from monoloc.server.storage.models import Camera


@dataclass(frozen=True)
class CameraRecord:
    """A registered camera: its id and name, the intrinsics with their lens, the key that
    registered it (None once that key's row is gone) and when."""

    id: int
    name: str
    intrinsics: CameraIntrinsics
    key_id: int | None
    created_at: datetime


def _record(row: Camera) -> CameraRecord:
    lens = None
    if row.distortion_model is not None:
        lens = LensDistortion(row.distortion_model, tuple(row.distortion or ()))
    intrinsics = CameraIntrinsics(row.fx, row.fy, row.cx, row.cy, row.width_px, row.height_px, lens)
    return CameraRecord(row.id, row.name, intrinsics, row.key_id, row.created_at)


def create_camera(
    session: Session, name: str, intrinsics: CameraIntrinsics, key_id: int | None
) -> CameraRecord:
    """Store a new camera (``intrinsics`` already checked by CameraIntrinsics)."""
    lens = intrinsics.distortion
    row = Camera(
        name=name.strip(),
        fx=float(intrinsics.fx),
        fy=float(intrinsics.fy),
        cx=float(intrinsics.cx),
        cy=float(intrinsics.cy),
        width_px=int(intrinsics.width_px),
        height_px=int(intrinsics.height_px),
        distortion_model=None if lens is None else lens.model,
        distortion=None if lens is None else list(lens.coefficients),
        key_id=key_id,
    )
    session.add(row)
    session.flush()
    return _record(row)


def get_camera(session: Session, camera_id: int) -> CameraRecord:
    row = session.get(Camera, camera_id)
    if row is None:
        raise NotFoundError(
            f"camera {camera_id} does not exist (register the camera: POST /v1/cameras)"
        )
    return _record(row)


def list_cameras(session: Session, limit: int = 1000) -> list[CameraRecord]:
    rows = session.scalars(select(Camera).order_by(Camera.id).limit(limit))
    return [_record(row) for row in rows]


def delete_camera(session: Session, camera_id: int) -> CameraRecord:
    """Delete a camera; its record as it was."""
    row = session.get(Camera, camera_id)
    if row is None:
        raise NotFoundError(f"camera {camera_id} does not exist")
    record = _record(row)
    session.delete(row)
    session.flush()
    return record

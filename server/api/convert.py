"""Storage records and pipeline results -> response schemas where the shape changes
(nesting, arrays, records combined), plus the error responses every route documents. A
record a schema reads as it is needs no mapper: ``XPublic.model_validate(record)``."""

from __future__ import annotations

from typing import Any

import numpy as np

from monoloc.core.geo import GeoPose, GeoReference
from monoloc.server.api import schemas as s
from monoloc.server.api.schemas_localize import (
    GeoPosePublic,
    HypothesisPublic,
    LocalizeResponse,
    RejectedPublic,
    RetrievedPublic,
)
from monoloc.server.localize import LocalizationResult, PoseHypothesis
from monoloc.server.storage.records import EntrySummary, MapRecord, VocabularyRecord
from monoloc.server.vision.features import rule_is_current


def _err(code: str, message: str) -> dict[str, Any]:
    return {"error": {"code": code, "message": message}}


def error_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` for the given error statuses, each with an example."""
    examples = {
        400: ("bad_request", "archive member '../etc/passwd' leaves the upload directory"),
        401: ("unauthorized", "missing API key: send it in the X-API-Key header"),
        403: ("forbidden", "this API key lacks the 'admin' scope this route needs"),
        404: ("not_found", "map 7 does not exist"),
        408: (
            "request_timeout",
            "the request body did not arrive in time (nothing of it arrived for 30 s); "
            "send it again",
        ),
        409: ("conflict", "a map named 'kitti-00' already exists"),
        413: ("payload_too_large", "request body exceeds the limit of 536870912 bytes"),
        415: ("unsupported_media_type", "image is not a PNG or JPEG image"),
        422: ("invalid_input", "T_world_from_cam: expected 12 (3x4) or 16 (4x4) numbers"),
        503: ("overloaded", "the read lane is full (33 requests in flight); retry after 1 s"),
        507: (
            "insufficient_storage",
            "run.tar needs 104857600 more bytes of disk, but the uploads being unpacked now "
            "hold 10737418240 of MONOLOC_UPLOADS_DISK_QUOTA_BYTES=10737418240; retry after "
            "the Retry-After seconds",
        ),
    }
    return {
        status: {
            "model": s.ErrorResponse,
            "content": {"application/json": {"example": _err(*examples[status])}},
        }
        for status in statuses
    }


AUTH_ERRORS = error_responses(401, 403)


def map_public(m: MapRecord, vocab: VocabularyRecord) -> s.MapPublic:
    return s.MapPublic(
        id=m.id,
        name=m.name,
        camera=s.Camera.model_validate(m.camera),
        vocabulary=s.VocabularyPublic.model_validate(vocab),
        version=m.version,
        n_entries=m.n_entries,
        calibrated=bool(m.calibration),
        calibrated_conditions=sorted((m.calibration or {}).get("conditions") or {}),
        geo_reference=geo_reference_public(m.geo_reference),
        features=m.features,
        features_current=rule_is_current(m.features),
        created_at=m.created_at,
        updated_at=m.updated_at,
    )


def geo_reference_public(stored: dict[str, Any] | None) -> s.GeoReferencePublic | None:
    """The stored reference (``GeoReference.to_dict``) as the API shows it."""
    if stored is None:
        return None
    origin = stored.get("origin")
    return s.GeoReferencePublic(
        origin=None if origin is None else s.GeoOriginSpec(**origin),
        T_ecef_from_world=list(stored["T_ecef_from_world"]),
    )


def planar(pose: np.ndarray) -> s.PlanarPose:
    return s.PlanarPose(x_m=float(pose[0]), y_m=float(pose[1]), yaw_rad=float(pose[2]))


def _entry_fields(e: EntrySummary) -> dict[str, Any]:
    """The summary's fields, its planar pose nested as the API shows it."""
    return {**vars(e), "pose": s.PlanarPose(x_m=e.x_m, y_m=e.y_m, yaw_rad=e.yaw_rad)}


def entry_public(e: EntrySummary) -> s.EntryPublic:
    return s.EntryPublic.model_validate(_entry_fields(e))


def entry_detail(e: EntrySummary, T_world_from_cam: np.ndarray) -> s.EntryDetail:
    T = np.asarray(T_world_from_cam, float).ravel().tolist()
    return s.EntryDetail.model_validate({**_entry_fields(e), "T_world_from_cam": T})


def hypothesis(h: PoseHypothesis, geopose: GeoPose | None = None) -> HypothesisPublic:
    return HypothesisPublic(
        geopose=None if geopose is None else GeoPosePublic.model_validate(geopose.to_json()),
        entry_id=h.entry_id,
        pose=planar(h.pose_world),
        entry_pose=planar(h.entry_pose_world),
        T_world_from_cam=np.asarray(h.T_world_from_cam, float).ravel().tolist(),
        e_vlad=h.e_vlad,
        n_inliers=h.n_inliers,
        n_matches=h.n_matches,
        reprojection_error_px=h.reprojection_error_px,
        joint=h.joint,
        entry_ids=list(h.entry_ids),
        method=h.method,
        entry_tags=list(h.entry_tags),
        pose_covariance=None
        if h.covariance_px1 is None
        else np.asarray(h.covariance_px1, float).ravel().tolist(),
    )


def localize_response(
    map_id: int,
    map_version: int,
    result: LocalizationResult,
    timings_ms: dict[str, float],
    seed: int,
    geo: GeoReference | None = None,
) -> LocalizeResponse:
    """The answer; with ``geo`` (the map's reference) every hypothesis carries a GeoPose."""
    ordered = sorted(result.hypotheses, key=lambda h: (-h.n_inliers, h.entry_id))
    geoposes: list[GeoPose | None] = [None] * len(ordered)
    if geo is not None and ordered:
        geoposes = list(geo.geoposes(np.stack([h.T_world_from_cam for h in ordered])))
    return LocalizeResponse(
        map_id=map_id,
        map_version=map_version,
        hypotheses=[hypothesis(h, g) for h, g in zip(ordered, geoposes, strict=True)],
        retrieved=[
            RetrievedPublic(entry_id=int(i), distance=float(d))
            for i, d in zip(result.retrieved_ids, result.retrieved_distances, strict=True)
        ],
        rejected=len(result.rejected),
        rejected_entries=[RejectedPublic(entry_id=i, reason=r) for i, r in result.rejected],
        n_features=result.n_features,
        timings_ms={k: round(float(v), 3) for k, v in timings_ms.items()},
        seed=seed,
    )

"""Measurement-model calibration per map (docs/method.md section 7): get (localize: the
vehicle downloads it), put and delete (map:write), and calibration jobs (map:write): a
training run uploaded like a mapping run (``monoloc.server.api.uploads``: one tar/zip archive or
a multipart file set, KITTI or TUM) is fitted by a ``calibrate`` job, which stores the
parameters with their provenance. The training run is not added to the map.

An uncalibrated map answers ``monoloc.core.measurement.MeasurementModel``'s documented
defaults with ``"calibrated": false`` and ``"source": "defaults"``.

Conditions (``monoloc.server.calibration_conditions``): a calibration job with
``condition=night`` fits its training run, recorded in that condition (e.g. a night run
against the map's night entries), as the model of the ``night`` condition; hypotheses
from entries tagged ``night`` are then weighed by it. It needs the base calibration
(409 otherwise) and leaves it untouched; ``DELETE .../calibration/conditions/{name}``
removes one.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated, Any

import anyio
from fastapi import APIRouter, Form, Path, UploadFile, status
from pydantic import BaseModel, ConfigDict
from sqlalchemy.orm import Session

from monoloc.core.measurement import MeasurementModel
from monoloc.server import calibration_conditions as conditions
from monoloc.server.api.archives import Unpacked
from monoloc.server.api.convert import AUTH_ERRORS, error_responses
from monoloc.server.api.deps import AppState, MapWriteKey, ReadKey, SessionDep, StateDep
from monoloc.server.api.guard import GuardedRoute, body_limit
from monoloc.server.api.params import MapId
from monoloc.server.api.schemas import (
    TAG_PATTERN,
    CalibrationPublic,
    CalibrationUpdate,
    JobPublic,
)
from monoloc.server.api.uploads import (
    RunArchive,
    RunFiles,
    RunFormat,
    RunFrames,
    RunSequence,
    RunUpload,
    check_upload_parts,
    store_upload,
    upload_name,
)
from monoloc.server.calibrate import (
    CalibrationConfig,
    calibration_fit,
    check_run_length,
    neighbour_vlad_distances,
)
from monoloc.server.jobs import store as jobs_repo
from monoloc.server.jobs.calibration import JOB_KIND, CalibrationParams
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.records import JobRecord

ConditionName = Annotated[
    str, Path(pattern=TAG_PATTERN, description="The condition: an entry tag, e.g. night.")
]
router = APIRouter(
    prefix="/v1/maps/{map_id}/calibration", tags=["calibration"], route_class=GuardedRoute
)


class CalibrationJobAccepted(BaseModel):
    """The queued calibration job and what the upload held."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "job": {
                        "id": 9,
                        "kind": "calibrate",
                        "map_id": 1,
                        "run_id": None,
                        "state": "queued",
                        "progress": 0.0,
                        "message": "queued",
                        "error": None,
                        "params": {"format": "kitti", "sequence": "05", "k": 10, "seed": 0},
                        "result": None,
                        "created_at": "2024-05-01T12:00:00Z",
                        "updated_at": "2024-05-01T12:00:00Z",
                        "finished_at": None,
                    },
                    "n_frames": 2761,
                    "n_files": 5524,
                    "total_bytes": 1_400_000_000,
                }
            ]
        }
    )
    job: JobPublic
    n_frames: int
    n_files: int
    total_bytes: int


def _public(
    calibration: dict[str, Any] | None, fit: dict[str, Any] | None = None
) -> CalibrationPublic:
    if not calibration:
        model = MeasurementModel()
        return CalibrationPublic(
            **{k: v for k, v in model.to_dict().items() if k != "source"},
            provenance={"note": "documented defaults (monoloc.core.measurement.MeasurementModel)"},
            calibrated=False,
            source="defaults",
        )
    values = MeasurementModel.from_dict(calibration).to_dict()
    del values["source"]
    return CalibrationPublic(
        **{**values, "conditions": conditions.public_conditions(calibration)},
        provenance=dict(calibration.get("provenance") or {}),
        calibrated=True,
        source=str(calibration.get("source", "calibrated")),
        updated_at=calibration.get("updated_at"),
        fit=fit,
    )


def _fit(state: AppState, map_id: int, calibration: dict[str, Any] | None) -> dict | None:
    """How the calibration matches this map's entries (``calibrate.calibration_fit``);
    None without a calibration or entries."""
    if not calibration:
        return None
    index = state.registry.get(map_id).index
    distances = neighbour_vlad_distances(index.poses_world(), index.vlads_at)
    return calibration_fit(dict(calibration.get("provenance") or {}), distances)


@router.get(
    "",
    response_model=CalibrationPublic,
    responses={**AUTH_ERRORS, **error_responses(404)},
    summary="Get the calibration",
)
def get_calibration(
    map_id: MapId, session: SessionDep, state: StateDep, _key: ReadKey
) -> CalibrationPublic:
    """mu1, Sigma1, mu2, Sigma2 (and the outlier floor) with their provenance, and how
    they fit this map (``fit``: its VLAD distances against the training run's)."""
    calibration = maps_repo.get_map(session, map_id).calibration
    return _public(calibration, _fit(state, map_id, calibration))


@router.put(
    "",
    response_model=CalibrationPublic,
    responses={**AUTH_ERRORS, **error_responses(404, 422)},
    summary="Set the calibration",
)
def put_calibration(
    map_id: MapId, body: CalibrationUpdate, session: SessionDep, _key: MapWriteKey
) -> CalibrationPublic:
    """Store parameters computed elsewhere. Covariances must be symmetric positive
    definite (422 otherwise); so must each condition's, which cannot have conditions of
    its own."""
    values = body.model_dump()
    now = datetime.now(UTC).isoformat()
    values.update(
        source="put", updated_at=now, conditions=conditions.put_conditions(body.conditions, now)
    )
    record = maps_repo.set_calibration(session, map_id, conditions.checked(values))
    session.commit()
    return _public(record.calibration)


@router.delete(
    "",
    response_model=CalibrationPublic,
    responses={**AUTH_ERRORS, **error_responses(404)},
    summary="Forget the calibration (back to defaults)",
)
def delete_calibration(map_id: MapId, session: SessionDep, _key: MapWriteKey) -> CalibrationPublic:
    record = maps_repo.set_calibration(session, map_id, None)
    session.commit()
    return _public(record.calibration)


@router.delete(
    "/conditions/{name}",
    response_model=CalibrationPublic,
    responses={**AUTH_ERRORS, **error_responses(404, 422)},
    summary="Forget one condition's calibration",
)
def delete_condition(
    map_id: MapId, name: ConditionName, session: SessionDep, _key: MapWriteKey
) -> CalibrationPublic:
    """Hypotheses from entries tagged ``name`` are weighed by the base calibration again
    (404 if the map has no calibration for that condition)."""
    name = conditions.condition_name(name)
    record = maps_repo.update_calibration(
        session, map_id, lambda stored: conditions.without_condition(stored, map_id, name)
    )
    session.commit()
    return _public(record.calibration)


def _store_job(
    state: AppState,
    map_id: int,
    params: CalibrationParams,
    archive: UploadFile | None,
    files: list[UploadFile] | None,
) -> tuple[JobRecord, int, Unpacked]:
    """Refuse a condition without a base calibration (before the upload is unpacked),
    unpack and validate the training run, refuse a too short one, record the job."""
    if params.condition is not None:
        with session_scope(state.sessions) as session:
            stored = maps_repo.get_map(session, map_id).calibration
        conditions.require_base(stored, map_id, params.condition)
    assert params.source_name is not None
    up = RunUpload(map_id, params.format, params.sequence, params.frames, params.source_name)

    def record(session: Session, source) -> tuple[JobRecord, int]:
        n_frames = len(source.frames)
        check_run_length(n_frames, params.config, f"the uploaded {up.format} run")
        job = jobs_repo.create_job(
            session,
            JOB_KIND,
            map_id=map_id,
            params=params.model_dump(mode="json"),
            message="queued",
        )
        return job, n_frames

    return store_upload(state, up, archive, files, record)


@router.post(
    "/jobs",
    response_model=CalibrationJobAccepted,
    openapi_extra=body_limit("archive"),
    status_code=status.HTTP_202_ACCEPTED,
    responses={**AUTH_ERRORS, **error_responses(400, 404, 413, 415, 422, 507)},
    summary="Calibrate from an uploaded training run (job)",
)
async def calibration_job(
    map_id: MapId,
    state: StateDep,
    _key: MapWriteKey,
    format: RunFormat,
    archive: RunArchive = None,
    files: RunFiles = None,
    sequence: RunSequence = None,
    frames: RunFrames = None,
    k: Annotated[
        int, Form(ge=1, le=100, description="Map entries per query, closest by pose.")
    ] = CalibrationConfig.k,
    seed: Annotated[int, Form(ge=0, description="RANSAC seed (a re-run repeats it).")] = 0,
    condition: Annotated[
        str | None,
        Form(
            pattern=TAG_PATTERN,
            description="Calibrate this condition's model (an entry tag, e.g. night) from a "
            "run recorded in it, instead of the base calibration, which the map must have "
            "(409 otherwise) and which is left untouched. Hypotheses from entries with the "
            "tag are weighed by it.",
        ),
    ] = None,
) -> CalibrationJobAccepted:
    """Maximum-likelihood mu1, Sigma1, mu2, Sigma2 from a training run that is not the
    test run (docs/method.md s. 7): a temporary map of every other frame, queried by the
    others against their k closest entries by pose, with the run's own camera and the
    map's vocabulary. Follow the job at /v1/jobs/{id}; when it is done,
    GET /v1/maps/{map_id}/calibration returns the parameters with ``calibrated: true``
    and their provenance. A run shorter than 2 (k - 1) + 2 frames is refused (422).
    With ``condition``, the parameters become ``conditions[condition]`` of the stored
    calibration; calibrating the base again keeps the conditions calibrated with the same
    vocabulary. The stored calibration selects the pose-error model of each hypothesis's
    own PnP covariance (every model is fitted and stored)."""
    check_upload_parts(archive, files)
    params = CalibrationParams.create(
        format=format,
        sequence=sequence,
        frames=frames,
        k=k,
        seed=seed,
        condition=condition,
        source_name=upload_name(archive),
        upload=True,
    )
    job, n_frames, unpacked = await anyio.to_thread.run_sync(
        _store_job, state, map_id, params, archive, files
    )
    state.jobs.submit(job.id)
    return CalibrationJobAccepted(
        job=JobPublic.model_validate(job),
        n_frames=n_frames,
        n_files=unpacked.n_files,
        total_bytes=unpacked.total_bytes,
    )

"""Measurement-model calibration per map (METHOD.md section 7): get (localize: the
vehicle downloads it), put and delete (map:write), and the place where calibration
training jobs start (map:write; answers 501 until the training handler is installed).

An uncalibrated map answers ``client.measurement.MeasurementModel``'s documented
defaults with ``"calibrated": false`` and ``"source": "defaults"``.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from fastapi import APIRouter, Response, status
from pydantic import BaseModel, ConfigDict

from client.measurement import MeasurementModel
from server.api import convert
from server.api.convert import AUTH_ERRORS, error_responses
from server.api.deps import LocalizeKey, MapWriteKey, SessionDep, StateDep
from server.api.errors import NotAvailableError
from server.api.schemas import CalibrationPublic, CalibrationUpdate, JobPublic
from server.storage import jobs as jobs_repo
from server.storage import maps as maps_repo
from server.storage import runs as runs_repo

router = APIRouter(prefix="/v1/maps/{map_id}/calibration", tags=["calibration"])

CALIBRATION_JOB_KIND = "calibrate"


class CalibrationJobCreate(BaseModel):
    """Which run of the map to train on; ``options`` go to the training handler."""

    model_config = ConfigDict(json_schema_extra={"examples": [{"run_id": 2, "options": {}}]})
    run_id: int
    options: dict[str, Any] = {}


def _public(calibration: dict[str, Any] | None) -> CalibrationPublic:
    if not calibration:
        model = MeasurementModel()
        return CalibrationPublic(
            **{k: v for k, v in model.to_dict().items() if k != "source"},
            provenance={"note": "documented defaults (client.measurement.MeasurementModel)"},
            calibrated=False,
            source="defaults",
        )
    model = MeasurementModel.from_dict(calibration)
    return CalibrationPublic(
        **{k: v for k, v in model.to_dict().items() if k != "source"},
        provenance=dict(calibration.get("provenance") or {}),
        calibrated=True,
        source=str(calibration.get("source", "calibrated")),
        updated_at=calibration.get("updated_at"),
    )


@router.get(
    "",
    response_model=CalibrationPublic,
    responses={**AUTH_ERRORS, **error_responses(404)},
    summary="Get the calibration",
)
def get_calibration(map_id: int, session: SessionDep, _key: LocalizeKey) -> CalibrationPublic:
    """mu1, Sigma1, mu2, Sigma2 (and the outlier floor) with their provenance."""
    return _public(maps_repo.get_map(session, map_id).calibration)


@router.put(
    "",
    response_model=CalibrationPublic,
    responses={**AUTH_ERRORS, **error_responses(404, 422)},
    summary="Set the calibration",
)
def put_calibration(
    map_id: int, body: CalibrationUpdate, session: SessionDep, _key: MapWriteKey
) -> CalibrationPublic:
    """Store parameters computed elsewhere. Covariances must be symmetric positive
    definite (422 otherwise)."""
    values = body.model_dump()
    MeasurementModel.from_dict(values)  # the client must be able to use them
    values.update(source="put", updated_at=datetime.now(UTC).isoformat())
    record = maps_repo.set_calibration(session, map_id, values)
    session.commit()
    return _public(record.calibration)


@router.delete(
    "",
    response_model=CalibrationPublic,
    responses={**AUTH_ERRORS, **error_responses(404)},
    summary="Forget the calibration (back to defaults)",
)
def delete_calibration(map_id: int, session: SessionDep, _key: MapWriteKey) -> CalibrationPublic:
    record = maps_repo.set_calibration(session, map_id, None)
    session.commit()
    return _public(record.calibration)


@router.post(
    "/jobs",
    response_model=JobPublic,
    status_code=status.HTTP_202_ACCEPTED,
    responses={**AUTH_ERRORS, **error_responses(404, 422, 501)},
    summary="Train the calibration from a run (job)",
)
def calibration_job(
    map_id: int,
    body: CalibrationJobCreate,
    session: SessionDep,
    state: StateDep,
    _key: MapWriteKey,
    response: Response,
) -> JobPublic:
    """Maximum-likelihood mu1, Sigma1, mu2, Sigma2 from a training run (METHOD.md s. 7),
    as a job. 501 while this build has no training handler (job kind 'calibrate')."""
    if CALIBRATION_JOB_KIND not in state.jobs.handlers:
        raise NotAvailableError(
            "calibration training is not available in this build yet; PUT the parameters instead"
        )
    maps_repo.get_map(session, map_id)
    if runs_repo.get_run(session, body.run_id).map_id != map_id:
        from client.errors import InvalidInputError

        raise InvalidInputError(f"run {body.run_id} is not a run of map {map_id}")
    job = jobs_repo.create_job(
        session,
        CALIBRATION_JOB_KIND,
        map_id=map_id,
        run_id=body.run_id,
        params={"run_id": body.run_id, "options": body.options},
    )
    session.commit()
    state.jobs.submit(job.id)
    return convert.job_public(job)

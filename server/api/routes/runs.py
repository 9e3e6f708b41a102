"""Mapping runs (map:write): upload a KITTI sequence (with LiDAR scans, or a stereo pair:
``depth_from=stereo``) or a TUM RGB-D run, as one archive
(tar, tar.gz/bz2/xz, zip) or as a multipart set of files whose names are their paths
inside the run (``sequences/00/image_0/000000.png``); list and get runs.

The job's parameters are checked first (422 naming the field), then the upload is
unpacked into ``uploads/.incoming-<random>`` with the archive limits, opened and
validated by the reader (calibration, poses, file counts: 422 naming the file). Only
then are the run and its ingestion job stored, and the directory renamed to
``uploads/<job id>``: a rejected upload leaves nothing behind (``monoloc.server.api.uploads``,
shared with the calibration route).
"""

from __future__ import annotations

from typing import Annotated, Literal

import anyio
from fastapi import APIRouter, Form, UploadFile, status
from sqlalchemy.orm import Session

from monoloc.core.errors import NotFoundError
from monoloc.server.api.archives import Unpacked
from monoloc.server.api.convert import AUTH_ERRORS, error_responses
from monoloc.server.api.deps import AppState, MapWriteKey, SessionDep, StateDep
from monoloc.server.api.guard import GuardedRoute, body_limit
from monoloc.server.api.params import MapId, RunId
from monoloc.server.api.schemas import (
    RUN_KIND_PATTERN,
    TAG_LIST_PATTERN,
    JobPublic,
    RunPublic,
    UploadAccepted,
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
from monoloc.server.jobs import store as jobs_repo
from monoloc.server.jobs.ingest import JOB_KIND, IngestParams
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage import runs as runs_repo
from monoloc.server.storage.records import JobRecord, RunRecord

router = APIRouter(prefix="/v1/maps/{map_id}/runs", tags=["runs"], route_class=GuardedRoute)


def _store(
    state: AppState,
    map_id: int,
    kind: str,
    params: IngestParams,
    archive: UploadFile | None,
    files: list[UploadFile] | None,
) -> tuple[JobRecord, RunRecord, Unpacked]:
    """Unpack, validate, then record the run and its job (blocking; runs in a thread)."""
    up = RunUpload(
        map_id, params.format, params.sequence, params.frames, params.source_name, params.depth_from
    )

    def record(session: Session, source) -> tuple[JobRecord, RunRecord]:
        n_frames = len(source.frames) + sum(getattr(source, "read_skips", {}).values())
        run = runs_repo.create_run(
            session,
            map_id,
            kind=kind,
            source_format=params.format,
            source_name=params.source_name,
            frames_total=n_frames,
        )
        job = jobs_repo.create_job(
            session,
            JOB_KIND,
            map_id=map_id,
            run_id=run.id,
            params=params.model_dump(mode="json"),
            message="queued",
        )
        return job, run

    return store_upload(state, up, archive, files, record)


@router.post(
    "",
    response_model=UploadAccepted,
    openapi_extra=body_limit("archive"),
    status_code=status.HTTP_202_ACCEPTED,
    responses={**AUTH_ERRORS, **error_responses(400, 404, 413, 415, 422, 507)},
    summary="Upload a mapping run (ingested by a job)",
)
async def upload_run(
    map_id: MapId,
    state: StateDep,
    _key: MapWriteKey,
    format: RunFormat,
    archive: RunArchive = None,
    files: RunFiles = None,
    sequence: RunSequence = None,
    frames: RunFrames = None,
    kind: Annotated[
        str,
        Form(
            pattern=RUN_KIND_PATTERN,
            description="map, offcenter, night, ... (a night run tags its entries night, an "
            "offcenter run off-center)",
        ),
    ] = "map",
    train_vocabulary: Annotated[
        bool,
        Form(
            description="First train the map's vocabulary (k = 64) on this run and switch "
            "the map to it (for a map's first run)."
        ),
    ] = False,
    tags: Annotated[
        str | None,
        Form(
            pattern=TAG_LIST_PATTERN,
            description="Comma-separated tags for every entry, e.g. night,off-center.",
        ),
    ] = None,
    depth_from: Annotated[
        Literal["lidar", "stereo"],
        Form(
            description="KITTI runs: keypoint depth from the LiDAR scans (velodyne/) or from "
            "the stereo pair (image_1/ and P1 in calib.txt; the upload then needs no scans)."
        ),
    ] = "lidar",
    register_to_map: Annotated[
        bool,
        Form(
            description="Register the run to the map's entries before adding it: localize "
            "its frames against them near their written poses and move its poses by the "
            "smoothed difference (two runs' GNSS/INS disagree by centimetres to "
            "decimetres). The job's result and the run's `registration` report the "
            "correction."
        ),
    ] = False,
) -> UploadAccepted:
    """Stores the upload and queues its ingestion; follow the job at /v1/jobs/{id}."""
    check_upload_parts(archive, files)
    runs_repo.check_kind(kind, "run")
    asked = [t for t in (tags or "").split(",") if t.strip()]
    params = IngestParams.create(
        format=format,
        sequence=sequence,
        frames=frames,
        depth_from=depth_from,
        source_name=upload_name(archive),
        tags=runs_repo.tags_for_run(kind, asked),
        train_vocabulary=train_vocabulary,
        register_to_map=register_to_map,
    )
    job, run, unpacked = await anyio.to_thread.run_sync(
        _store, state, map_id, kind, params, archive, files
    )
    state.jobs.submit(job.id)
    return UploadAccepted(
        job=JobPublic.model_validate(job),
        run=RunPublic.model_validate(run),
        n_files=unpacked.n_files,
        total_bytes=unpacked.total_bytes,
    )


@router.get(
    "",
    response_model=list[RunPublic],
    responses={**AUTH_ERRORS, **error_responses(404)},
    summary="List a map's runs",
)
def list_runs(map_id: MapId, session: SessionDep, _key: MapWriteKey) -> list[RunPublic]:
    maps_repo.get_map(session, map_id)
    return [RunPublic.model_validate(r) for r in runs_repo.list_runs(session, map_id)]


@router.get(
    "/{run_id}",
    response_model=RunPublic,
    responses={**AUTH_ERRORS, **error_responses(404)},
    summary="Get a run",
)
def get_run(map_id: MapId, run_id: RunId, session: SessionDep, _key: MapWriteKey) -> RunPublic:
    run = runs_repo.get_run(session, run_id)
    if run.map_id != map_id:
        raise NotFoundError(f"run {run_id} does not exist in map {map_id}")
    return RunPublic.model_validate(run)

"""A job's parameters: one frozen, validated model per job kind (``IngestParams``,
``CalibrationParams``, ``VocabularyParams``, next to their handlers), built when the job
is created (:meth:`JobParams.create`: a bad one is the creator's error, 422 over HTTP)
and stored as the job row's JSON (``model_dump(mode="json")``). A handler reads its row
back with :meth:`JobParams.from_row`, so a resumed job does what the first attempt meant
to do; a row that cannot run here (written by another version of the server) fails its
job with the reason instead of running something else.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal, Self

from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator

from monoloc.core.errors import ConflictError, InvalidInputError
from monoloc.server.ingest.common import parse_frame_range
from monoloc.server.jobs.uploads import dataset_root, open_source
from monoloc.server.storage.records import JobRecord

RunFormat = Literal["kitti", "tum"]
DepthFrom = Literal["lidar", "stereo"]


def describe(exc: ValidationError) -> str:
    """The invalid fields of ``exc``, one ``field: why`` each."""
    parts = []
    for err in exc.errors():
        where = ".".join(str(p) for p in err["loc"]) or "parameters"
        parts.append(f"{where}: {err['msg'].removeprefix('Value error, ')}")
    return "; ".join(parts)


class JobParams(BaseModel):
    """What a job needs to run again; subclassed per job kind."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    @classmethod
    def create(cls, **values: Any) -> Self:
        """The parameters of a new job (None stands for a field's default);
        InvalidInputError naming each bad field (caused by the ValidationError)."""
        try:
            return cls.model_validate({k: v for k, v in values.items() if v is not None})
        except ValidationError as exc:
            raise InvalidInputError(f"invalid job parameter {describe(exc)}") from exc

    @classmethod
    def from_row(cls, job: JobRecord) -> Self:
        """The parameters stored in ``job``'s row; ConflictError naming the bad field of a
        row this server cannot run."""
        try:
            return cls.model_validate(cls.stored_shape(job, dict(job.params)))
        except ValidationError as exc:
            raise ConflictError(
                f"job {job.id} ({job.kind}) cannot run on this server, its parameter "
                f"{describe(exc)}: create a new job"
            ) from None

    @classmethod
    def stored_shape(cls, job: JobRecord, stored: dict[str, Any]) -> dict[str, Any]:
        """``stored`` in today's shape: the kinds whose rows changed shape override it."""
        return stored


class RunParams(JobParams):
    """How a job reads its recorded run: its layout, a KITTI sequence (of an upload that
    holds several), a frame range ``A:B`` (Python slice) and where a KITTI run's keypoint
    depth comes from (a TUM run has its depth images)."""

    format: RunFormat
    sequence: str | None = Field(default=None, max_length=64)
    frames: str | None = None
    depth_from: DepthFrom = "lidar"

    @field_validator("frames")
    @classmethod
    def _frame_range(cls, frames: str | None) -> str | None:
        try:
            parse_frame_range(frames)
        except InvalidInputError as exc:
            raise ValueError(str(exc)) from None
        return frames

    @field_validator("depth_from")
    @classmethod
    def _depth_of_kitti(cls, depth_from: str, info: ValidationInfo) -> str:
        fmt = info.data.get("format")
        if depth_from != "lidar" and fmt not in (None, "kitti"):
            raise ValueError(f"{depth_from} depth is for KITTI runs; a {fmt} run has its own")
        return depth_from

    def open_upload(self, upload: Path):
        """The reader's view of the run unpacked under ``upload``."""
        return open_source(
            self.format, dataset_root(upload), self.sequence, self.frames, self.depth_from
        )

"""The ``ingest`` job kind: a mapping run uploaded as files is added to its map
(idempotent by image hash, so a resumed job adds only the frames that were missing),
optionally training the map's vocabulary on it first (``train_vocabulary``: seeded, so a
resumed job trains the same one) and registering the run to the map
(``register_to_map``: a resumed job registers to the same entries, so it finds the same
correction). Its parameters (:class:`IngestParams`) are read from the job row, so a
resumed job does what the first attempt meant to do.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

from pydantic import field_validator

from monoloc.core.errors import ConflictError, InvalidInputError
from monoloc.core.registration import RegistrationConfig
from monoloc.server.ingest.pipeline import IngestConfig, ingest_run
from monoloc.server.ingest.vocab import change_map_vocabulary_detailed, train_map_vocabulary
from monoloc.server.jobs.context import JobContext, JobInterruptedError
from monoloc.server.jobs.params import RunParams
from monoloc.server.storage.entry_checks import normalise_tags

JOB_KIND = "ingest"


class IngestParams(RunParams):
    """An uploaded mapping run's ingestion: how to read it (``RunParams``), the name it is
    known by (the upload's, never a server path), the tags of its entries (its kind's
    included), and whether the map's vocabulary is trained on it first and the run
    registered to the map's entries."""

    source_name: str
    tags: tuple[str, ...] = ()
    train_vocabulary: bool = False
    register_to_map: bool = False
    upload: bool = True

    @field_validator("tags")
    @classmethod
    def _tags(cls, tags: tuple[str, ...]) -> tuple[str, ...]:
        try:
            return tuple(normalise_tags(tags))
        except InvalidInputError as exc:
            raise ValueError(str(exc)) from None


@dataclass(frozen=True)
class _NamedSource:
    """What vocabulary training reads of a source, under a public name."""

    frames: list
    format: str
    name: str


def _train_vocabulary(ctx: JobContext, source, source_name: str) -> dict[str, Any]:
    """Train a vocabulary on the run (k = 64, seeded: a resumed job trains the same one)
    and switch the map to it before its frames are ingested."""
    ctx.progress(0.0, "training the map's vocabulary on this run", force=True)
    # The description names the run by its upload, not by the server's temporary path.
    named = _NamedSource(source.frames, source.format, f"{source_name} (job {ctx.job.id})")
    record = train_map_vocabulary(ctx.sessions, named)
    change = change_map_vocabulary_detailed(
        ctx.sessions,
        ctx.job.map_id,
        record.id,
        registry=ctx.registry,
        should_stop=ctx.should_stop,
    )
    if change.stopped:
        raise JobInterruptedError("stopped while switching vocabularies; resume to continue")
    return {
        "vocabulary_id": record.id,
        "vocabulary_hash": record.version_hash,
        "recomputed_entries": change.recomputed,
    }


def run_ingest(ctx: JobContext) -> dict[str, Any]:
    """Ingest the job's uploaded run into its map; the result is the ingestion summary
    (with the trained vocabulary when ``train_vocabulary`` was asked for)."""
    job = ctx.job
    params = IngestParams.from_row(job)
    if job.map_id is None or job.run_id is None:
        raise ConflictError(f"the map or run of job {job.id} was deleted")
    upload = ctx.upload_dir()
    if upload is None or not upload.is_dir():
        raise ConflictError(f"the upload of job {job.id} is gone; upload the run again")
    source = params.open_upload(upload)
    vocabulary = (
        _train_vocabulary(ctx, source, params.source_name) if params.train_vocabulary else None
    )

    def progress(done: int, total: int) -> None:
        ctx.progress(done / max(total, 1), f"frame {done} of {total}")

    summary = ingest_run(
        ctx.sessions,
        job.map_id,
        source,
        run_id=job.run_id,
        registry=ctx.registry,
        tags=params.tags,
        progress=progress,
        should_stop=ctx.should_stop,
        config=IngestConfig(
            workers=ctx.settings.worker_threads,
            register=RegistrationConfig() if params.register_to_map else None,
        ),
    )
    if summary.interrupted:
        raise JobInterruptedError(
            f"stopped after {summary.frames_done} of {summary.frames_total} frames; resume "
            "to continue"
        )
    result = asdict(summary)
    if vocabulary is not None:
        result["vocabulary"] = vocabulary
    return result

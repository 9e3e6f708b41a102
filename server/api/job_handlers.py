"""The job kinds the server runs: ``ingest`` (a mapping run uploaded as files,
optionally training the map's vocabulary on it first), ``vocabulary`` (switch a map
to another vocabulary; every VLAD is recomputed) and ``calibrate`` (fit the map's
measurement model on an uploaded training run, METHOD.md section 7). Each handler reads
its parameters from the job row, so a resumed job does what the first attempt meant to
do; all are idempotent (entries by image hash, VLADs by vocabulary id, a calibration
replaces the previous one and is seeded).

Uploaded images are deleted when their job is done, so a later vocabulary change
recomputes the VLADs of API-uploaded entries from their stored descriptors (counted as
``approximate`` in the result). Train a map's vocabulary with its first upload
(``train_vocabulary``) to avoid that.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from monoloc.core.errors import ConflictError, InvalidInputError
from monoloc.server.api.archives import dataset_root
from monoloc.server.api.jobs import JobContext, JobHandler, JobInterruptedError


def open_source(fmt: str, root: Path, sequence: str | None, frames: str | None):
    """The reader's view of an unpacked run: a KittiSequence or a TumRun (validated)."""
    from monoloc.server.ingest.common import parse_frame_range

    frame_range = parse_frame_range(frames)
    if fmt == "kitti":
        from monoloc.server.ingest.kitti import read_kitti_sequence

        return read_kitti_sequence(root, sequence=sequence, frames=frame_range)
    if fmt == "tum":
        from monoloc.server.ingest.tum import read_tum_run

        return read_tum_run(root, frames=frame_range)
    raise InvalidInputError(f"unknown run format {fmt!r}: use kitti or tum")


@dataclass(frozen=True)
class _NamedSource:
    """What vocabulary training reads of a source, under a public name."""

    frames: list
    format: str
    name: str


def _train_vocabulary(ctx: JobContext, source) -> dict[str, Any]:
    """Train a vocabulary on the run (k = 64, seeded: a resumed job trains the same one)
    and switch the map to it before its frames are ingested."""
    from monoloc.server.ingest.vocab import change_map_vocabulary_detailed, train_map_vocabulary

    ctx.progress(0.0, "training the map's vocabulary on this run", force=True)
    # The description names the run by its upload, not by the server's temporary path.
    named = _NamedSource(
        source.frames,
        source.format,
        f"{ctx.job.params.get('source_name', 'upload')} (job {ctx.job.id})",
    )
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
    from monoloc.server.ingest.pipeline import IngestConfig, ingest_run

    job = ctx.job
    if job.map_id is None or job.run_id is None:
        raise ConflictError(f"the map or run of job {job.id} was deleted")
    upload = ctx.upload_dir()
    if upload is None or not upload.is_dir():
        raise ConflictError(f"the upload of job {job.id} is gone; upload the run again")
    params = job.params
    source = open_source(
        params["format"], dataset_root(upload), params.get("sequence"), params.get("frames")
    )
    vocabulary = _train_vocabulary(ctx, source) if params.get("train_vocabulary") else None

    def progress(done: int, total: int) -> None:
        ctx.progress(done / max(total, 1), f"frame {done} of {total}")

    summary = ingest_run(
        ctx.sessions,
        job.map_id,
        source,
        run_id=job.run_id,
        registry=ctx.registry,
        tags=tuple(params.get("tags") or ()),
        progress=progress,
        should_stop=ctx.should_stop,
        config=IngestConfig(workers=ctx.settings.worker_threads),
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


def run_vocabulary(ctx: JobContext) -> dict[str, Any]:
    """Switch the map to another stored vocabulary and recompute every VLAD (from the
    entry's original image when the server still has it, else from its stored
    descriptors; ``approximate`` counts those). Resumable."""
    from monoloc.server.ingest.vocab import change_map_vocabulary_detailed

    job = ctx.job
    if job.map_id is None:
        raise ConflictError(f"the map of job {job.id} was deleted")

    def progress(done: int, total: int) -> None:
        ctx.progress(done / max(total, 1), f"{done} of {total} entries recomputed")

    change = change_map_vocabulary_detailed(
        ctx.sessions,
        job.map_id,
        int(job.params["vocabulary_id"]),
        registry=ctx.registry,
        progress=progress,
        should_stop=ctx.should_stop,
    )
    if change.stopped:
        raise JobInterruptedError("stopped before every VLAD was recomputed; resume to continue")
    return asdict(change)


def run_calibration(ctx: JobContext) -> dict[str, Any]:
    """Fit the measurement model on the uploaded training run (its own intrinsics, the
    map's vocabulary) and store it on the map; the run is not added to the map. A stop
    request ends the job ``interrupted``; resuming it calibrates again from the start."""
    from monoloc.server.calibrate import CalibrationConfig
    from monoloc.server.calibrate_jobs import calibrate_map, job_result

    job = ctx.job
    if job.map_id is None:
        raise ConflictError(f"the map of job {job.id} was deleted")
    upload = ctx.upload_dir()
    if upload is None:
        raise ConflictError(
            f"job {job.id} was started by `monoloc map calibrate` (no upload): run it again"
        )
    if not upload.is_dir():
        raise ConflictError(f"the upload of job {job.id} is gone; upload the run again")
    params = job.params
    source = open_source(
        params["format"], dataset_root(upload), params.get("sequence"), params.get("frames")
    )

    def progress(done: int, total: int) -> None:
        if ctx.should_stop():
            raise JobInterruptedError(
                f"stopped at frame {done} of {total}; resume to calibrate again"
            )
        ctx.progress(done / max(total, 1), f"frame {done} of {total}", force=done == total)

    calibration = calibrate_map(
        ctx.sessions,
        job.map_id,
        source,
        config=CalibrationConfig(k=int(params.get("k", CalibrationConfig.k))),
        seed=int(params.get("seed", 0)),
        job_id=job.id,
        source_name=params.get("source_name") or "upload",
        progress=progress,
    )
    return job_result(calibration)


HANDLERS: dict[str, JobHandler] = {
    "ingest": run_ingest,
    "vocabulary": run_vocabulary,
    "calibrate": run_calibration,
}

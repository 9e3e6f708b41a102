"""The ``vocabulary`` job kind: switch a map to another vocabulary and recompute every
entry's VLAD (from the entry's original image when the server still has it, else from
its stored descriptors; ``approximate`` counts those). Run by the job runner
(:func:`run_vocabulary`, a stored vocabulary chosen over HTTP) or by ``monoloc map
vocab`` (:func:`run_vocabulary_job`, optionally training the vocabulary on a run first).

Uploaded images are deleted when their job is done, so a later vocabulary change
recomputes the VLADs of API-uploaded entries from their stored descriptors. Train a
map's vocabulary with its first upload (``train_vocabulary``) to avoid that.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from monoloc.core.errors import ConflictError
from monoloc.server.ingest.manage import find_map, resolve_vocabulary
from monoloc.server.ingest.vocab import (
    VocabularyChange,
    change_map_vocabulary_detailed,
    train_map_vocabulary,
)
from monoloc.server.jobs.context import JobContext, JobInterruptedError
from monoloc.server.jobs.lifecycle import Progress, run_recorded_job
from monoloc.server.jobs.progress import update_job_now
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.records import JobRecord
from monoloc.server.vision.vocabulary import VocabularyConfig

JOB_KIND = "vocabulary"


def _entries_recomputed(done: int, total: int) -> str:
    return f"{done} of {total} entries recomputed"


def run_vocabulary(ctx: JobContext) -> dict[str, Any]:
    """Switch the map to the stored vocabulary ``params["vocabulary_id"]`` and recompute
    every VLAD. Resumable."""
    job = ctx.job
    if job.map_id is None:
        raise ConflictError(f"the map of job {job.id} was deleted")

    def progress(done: int, total: int) -> None:
        ctx.progress(done / max(total, 1), _entries_recomputed(done, total))

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


def run_vocabulary_job(
    session_factory: sessionmaker[Session],
    map_ref: str | int,
    *,
    source=None,
    vocabulary: str | None = None,
    max_images: int = 300,
    seed: int = 0,
    registry=None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[JobRecord, VocabularyChange]:
    """Train a vocabulary on ``source`` (or take ``vocabulary``: id, hash or default) and
    switch the map to it, recomputing its VLADs; all recorded as one job."""
    record = find_map(session_factory, map_ref)
    params = {
        "vocabulary": vocabulary,
        "train_from": getattr(source, "name", None),
        "max_images": max_images,
        "seed": seed,
    }

    def work(job: JobRecord, report: Progress) -> VocabularyChange:
        if source is not None:
            update_job_now(session_factory, job.id, message=f"training on {source.name}")
            vocab = train_map_vocabulary(
                session_factory, source, VocabularyConfig(seed=seed), max_images=max_images
            )
        else:
            with session_scope(session_factory) as session:
                vocab = resolve_vocabulary(session, vocabulary or "default")
        return change_map_vocabulary_detailed(
            session_factory, record.id, vocab.id, registry=registry, progress=report
        )

    return run_recorded_job(
        session_factory,
        JOB_KIND,
        map_id=record.id,
        params=params,
        started="starting",
        describe_progress=_entries_recomputed,
        work=work,
        result_of=asdict,
        progress=progress,
    )

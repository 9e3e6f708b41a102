"""Vocabulary change as a durable job (recorded in the jobs table: state, progress,
message, error, result), for the CLI; the HTTP API runs the same functions in its own
job runner."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict

from sqlalchemy.orm import Session, sessionmaker

from monoloc.server.ingest.manage import find_map, resolve_vocabulary
from monoloc.server.ingest.vocab import (
    VocabularyChange,
    change_map_vocabulary_detailed,
    train_map_vocabulary,
)
from monoloc.server.job_progress import progress_recorder, update_job_now
from monoloc.server.storage import jobs as jobs_repo
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.records import JobRecord
from monoloc.server.vision.vocabulary import VocabularyConfig

JOB_KIND = "vocabulary"


_update = update_job_now


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
    with session_scope(session_factory) as session:
        job = jobs_repo.create_job(
            session, JOB_KIND, map_id=record.id, params=params, message="queued"
        )
    _update(session_factory, job.id, state="running", message="starting")
    report = progress_recorder(
        session_factory,
        job.id,
        lambda done, total: f"{done} of {total} entries recomputed",
        progress,
    )

    try:
        if source is not None:
            _update(session_factory, job.id, message=f"training on {source.name}")
            vocab = train_map_vocabulary(
                session_factory, source, VocabularyConfig(seed=seed), max_images=max_images
            )
        else:
            with session_scope(session_factory) as session:
                vocab = resolve_vocabulary(session, vocabulary or "default")
        change = change_map_vocabulary_detailed(
            session_factory, record.id, vocab.id, registry=registry, progress=report
        )
    except BaseException as exc:
        state = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
        _update(session_factory, job.id, state=state, error=str(exc) or type(exc).__name__)
        raise
    job = _update(session_factory, job.id, state="done", message="done", result=asdict(change))
    return job, change

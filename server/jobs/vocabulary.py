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
from typing import Any, Self

from pydantic import Field, model_validator
from sqlalchemy.orm import Session, sessionmaker

from monoloc.core.errors import ConflictError, InvalidInputError
from monoloc.server.ingest.manage import find_map, resolve_vocabulary
from monoloc.server.ingest.vocab import (
    DEFAULT_TRAINING_IMAGES,
    VocabularyChange,
    change_map_vocabulary_detailed,
    train_map_vocabulary,
)
from monoloc.server.jobs.context import JobContext, JobInterruptedError
from monoloc.server.jobs.lifecycle import Progress, run_recorded_job
from monoloc.server.jobs.params import JobParams
from monoloc.server.jobs.progress import update_job_now
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.records import JobRecord
from monoloc.server.vision.vocabulary import VocabularyConfig

JOB_KIND = "vocabulary"


class VocabularyTraining(JobParams):
    """A vocabulary trained on a run first (``monoloc map vocab --train-from``): the
    run's name, the images it spreads over, the k-means seed."""

    run: str
    max_images: int = Field(default=DEFAULT_TRAINING_IMAGES, ge=1)
    seed: int = Field(default=VocabularyConfig.seed, ge=0)


class VocabularyParams(JobParams):
    """A vocabulary change: to ``vocabulary`` as asked ('default', an id or a hash;
    ``vocabulary_id`` the stored one it resolved to, which the job runner needs) or to
    one trained on a run first (``train``)."""

    vocabulary: str | None = None
    vocabulary_id: int | None = Field(default=None, ge=1)
    train: VocabularyTraining | None = None

    @model_validator(mode="after")
    def _something_to_switch_to(self) -> Self:
        if self.vocabulary is None and self.train is None:
            raise ValueError("give the vocabulary to switch to, or a run to train one on")
        return self

    @classmethod
    def stored_shape(cls, job: JobRecord, stored: dict[str, Any]) -> dict[str, Any]:
        """Rows of ``monoloc map vocab`` from before the training had its own model
        (``train_from``, ``max_images`` and ``seed`` beside ``vocabulary``)."""
        if "train_from" not in stored:
            return stored
        training = {
            "run": stored.pop("train_from"),
            "max_images": stored.pop("max_images", None),
            "seed": stored.pop("seed", None),
        }
        if training["run"] is not None:
            stored["train"] = {k: v for k, v in training.items() if v is not None}
        return stored


def _entries_recomputed(done: int, total: int) -> str:
    return f"{done} of {total} entries recomputed"


def run_vocabulary(ctx: JobContext) -> dict[str, Any]:
    """Switch the map to the stored vocabulary ``vocabulary_id`` of the job's parameters
    and recompute every VLAD. Resumable."""
    job = ctx.job
    params = VocabularyParams.from_row(job)
    if job.map_id is None:
        raise ConflictError(f"the map of job {job.id} was deleted")
    if params.vocabulary_id is None:
        raise ConflictError(
            f"job {job.id} was started by `monoloc map vocab` (no stored vocabulary to switch "
            "to): run the command again"
        )

    def progress(done: int, total: int) -> None:
        ctx.progress(done / max(total, 1), _entries_recomputed(done, total))

    change = change_map_vocabulary_detailed(
        ctx.sessions,
        job.map_id,
        params.vocabulary_id,
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
    params: VocabularyParams,
    *,
    source=None,
    registry=None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[JobRecord, VocabularyChange]:
    """Train a vocabulary on ``source`` as ``params.train`` says (or take
    ``params.vocabulary``: id, hash or default) and switch the map to it, recomputing its
    VLADs; all recorded as one job."""
    record = find_map(session_factory, map_ref)
    train = params.train
    if (train is None) != (source is None):
        raise InvalidInputError("a vocabulary is trained on a source, or taken as asked")

    def work(job: JobRecord, report: Progress) -> VocabularyChange:
        if train is not None:
            update_job_now(session_factory, job.id, message=f"training on {source.name}")
            vocab = train_map_vocabulary(
                session_factory,
                source,
                VocabularyConfig(seed=train.seed),
                max_images=train.max_images,
            )
        else:
            with session_scope(session_factory) as session:
                vocab = resolve_vocabulary(session, params.vocabulary)
        return change_map_vocabulary_detailed(
            session_factory, record.id, vocab.id, registry=registry, progress=report
        )

    return run_recorded_job(
        session_factory,
        JOB_KIND,
        map_id=record.id,
        params=params.model_dump(mode="json"),
        started="starting",
        describe_progress=_entries_recomputed,
        work=work,
        result_of=asdict,
        progress=progress,
    )

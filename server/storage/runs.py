"""Repository of mapping runs (one ingested recording each: status, counters, skip
reasons, error). Never commits.
"""

from __future__ import annotations

import re
from collections.abc import Mapping

from sqlalchemy import select
from sqlalchemy.orm import Session

from monoloc.core.errors import InvalidInputError, NotFoundError
from monoloc.server.storage.maps import get_map
from monoloc.server.storage.models import RUN_STATUSES, SOURCE_FORMATS, Run, utc_now
from monoloc.server.storage.records import RunRecord

KIND_RE = re.compile(r"^[a-z0-9][a-z0-9_-]{0,31}$")


# Runs of these kinds tag every entry they add (the CLI and the upload route alike).
KIND_TAGS = {"night": ("night",), "offcenter": ("off-center",)}


def tags_for_run(kind: str, tags: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """The tags a run's entries get: those asked for, then its kind's (no repeats)."""
    return tuple(dict.fromkeys((*tags, *KIND_TAGS.get(kind, ()))))


def check_kind(kind: str, what: str) -> str:
    if not isinstance(kind, str) or not KIND_RE.match(kind):
        raise InvalidInputError(f"invalid {what} kind {kind!r}: 1-32 of a-z, 0-9, '_', '-'")
    return kind


def check_count(value: int, name: str) -> int:
    if int(value) != value or value < 0:
        raise InvalidInputError(f"{name} must be a non-negative integer, got {value!r}")
    return int(value)


def _run_row(session: Session, run_id: int) -> Run:
    row = session.get(Run, run_id, populate_existing=True)
    if row is None:
        raise NotFoundError(f"run {run_id} does not exist")
    return row


def create_run(
    session: Session,
    map_id: int,
    *,
    kind: str,
    source_format: str,
    source_name: str = "",
    frames_total: int = 0,
) -> RunRecord:
    """Record a new run (status pending). ``kind`` e.g. map/offcenter/night/manual;
    ``source_format`` one of kitti, tum, single."""
    get_map(session, map_id)
    if source_format not in SOURCE_FORMATS:
        raise InvalidInputError(
            f"source_format must be one of {SOURCE_FORMATS}, got {source_format!r}"
        )
    row = Run(
        map_id=map_id,
        kind=check_kind(kind, "run"),
        source_format=source_format,
        source_name=str(source_name)[:512],
        status="pending",
        frames_total=check_count(frames_total, "frames_total"),
        skip_reasons={},
    )
    session.add(row)
    session.flush()
    return RunRecord.model_validate(row)


def get_run(session: Session, run_id: int) -> RunRecord:
    return RunRecord.model_validate(_run_row(session, run_id))


def list_runs(session: Session, map_id: int) -> list[RunRecord]:
    rows = session.scalars(
        select(Run)
        .where(Run.map_id == map_id)
        .order_by(Run.id)
        .execution_options(populate_existing=True)
    )
    return [RunRecord.model_validate(r) for r in rows]


def update_run(
    session: Session,
    run_id: int,
    *,
    status: str | None = None,
    frames_total: int | None = None,
    frames_done: int | None = None,
    entries_added: int | None = None,
    frames_skipped: int | None = None,
    skip_reasons: Mapping[str, int] | None = None,
    error: str | None = None,
    registration: Mapping[str, object] | None = None,
) -> RunRecord:
    """Set the given fields (absolute values; ``skip_reasons`` maps reason -> count;
    ``registration``: the run's registration summary)."""
    row = _run_row(session, run_id)
    if status is not None:
        if status not in RUN_STATUSES:
            raise InvalidInputError(f"run status must be one of {RUN_STATUSES}, got {status!r}")
        row.status = status
    for name, value in (
        ("frames_total", frames_total),
        ("frames_done", frames_done),
        ("entries_added", entries_added),
        ("frames_skipped", frames_skipped),
    ):
        if value is not None:
            setattr(row, name, check_count(value, name))
    if registration is not None:
        row.registration = dict(registration)
    if skip_reasons is not None:
        row.skip_reasons = {
            str(k): check_count(v, f"skip_reasons[{k!r}]") for k, v in skip_reasons.items()
        }
    if error is not None:
        row.error = error
    row.updated_at = utc_now()
    session.flush()
    return RunRecord.model_validate(row)

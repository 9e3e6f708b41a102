"""Uploaded recordings (a KITTI sequence or a TUM RGB-D run), shared by the routes that
turn one into a job: mapping runs (``routes/runs.py``, ingestion) and training runs
(``routes/calibration.py``, calibration).

An upload is one archive (tar, tar.gz/bz2/xz, zip) or a multipart set of files whose
names are their paths inside the run. It is unpacked into ``uploads/.incoming-<random>``
with the archive limits and disk quotas (``monoloc.server.api.archives``: 413 for an
upload too big in itself, 507 while the uploads unpacking at the same time hold the shared
quota), then opened and validated by the reader (422 naming the file, without the
server's paths). Only then does the caller record its rows (a run, a job)
in one transaction, and the directory is renamed ``uploads/<job id>``: a rejected upload
leaves nothing behind.
"""

from __future__ import annotations

import threading
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

from fastapi import File, Form, UploadFile
from sqlalchemy.orm import Session

from monoloc.core.errors import InvalidInputError
from monoloc.server.api.archives import (
    ArchiveLimits,
    Reservation,
    Unpacked,
    UploadSpace,
    save_file_set,
    unpack_archive,
)
from monoloc.server.api.bootstrap import INCOMING_PREFIX, uploads_dir
from monoloc.server.api.deps import AppState
from monoloc.server.api.schemas import FRAME_RANGE_PATTERN
from monoloc.server.jobs.uploads import dataset_root, open_source, remove_tree
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.records import JobRecord

# The upload fields shared by every route that takes a recorded run (mapping runs,
# calibration): one definition of each, so the routes document them alike.
RunFormat = Annotated[Literal["kitti", "tum"], Form(description="Layout of the run.")]
RunArchive = Annotated[UploadFile | None, File(description="tar/zip of the run.")]
RunFiles = Annotated[
    list[UploadFile] | None,
    File(description="Or: the run's files, each named by its relative path."),
]
RunSequence = Annotated[
    str | None,
    Form(max_length=64, description="KITTI sequence (e.g. 00) if the upload holds several."),
]
RunFrames = Annotated[
    str | None,
    Form(
        pattern=FRAME_RANGE_PATTERN,
        description="Frame range A:B (Python slice), e.g. 0:3860 for the mapping 85 % of KITTI 00.",
    ),
]

T = TypeVar("T")

# What a caller records for a validated upload: (session, source) -> (its job, anything).
RecordRows = Callable[[Session, Any], tuple[JobRecord, T]]


@dataclass(frozen=True)
class RunUpload:
    """Which map, how to read the upload, and the name it is known by (never a server
    path: the archive's file name, or ``files``)."""

    map_id: int
    format: str
    sequence: str | None
    frames: str | None
    source_name: str
    depth_from: str = "lidar"


def check_upload_parts(archive: UploadFile | None, files: list[UploadFile] | None) -> None:
    """Exactly one of ``archive`` and ``files`` (InvalidInputError otherwise)."""
    if (archive is None) == (not files):
        raise InvalidInputError("send either 'archive' (one tar/zip) or 'files', not both")


def upload_name(archive: UploadFile | None) -> str:
    return (archive.filename if archive is not None else "files") or "upload"


_SPACES: dict[Path, UploadSpace] = {}
_SPACES_LOCK = threading.Lock()


def upload_space(uploads: Path) -> UploadSpace:
    """The disk ledger of the uploads this process unpacks into ``uploads`` (one per
    directory, so that apps on other data folders, tests among them, do not share it)."""
    key = Path(uploads).resolve()
    with _SPACES_LOCK:
        return _SPACES.setdefault(key, UploadSpace())


def unpack_upload(
    state: AppState,
    staging: Path,
    archive: UploadFile | None,
    files: list[UploadFile] | None,
    reservation: Reservation | None = None,
) -> Unpacked:
    """Write the archive's members (or the file set) under ``staging``, with the limits,
    taking the disk from ``reservation``."""
    settings = state.settings
    limits = ArchiveLimits(
        settings.max_archive_members,
        settings.max_archive_bytes,
        settings.max_archive_ratio,
        settings.archive_ratio_allowance_bytes,
    )
    if archive is not None:
        what = archive.filename or "archive"
        return unpack_archive(archive.file, staging, limits, what, reservation)
    assert files is not None
    named = [(f.filename or "", f.file) for f in files]
    return save_file_set(named, staging, limits, "upload", reservation)


def open_uploaded_run(
    staging: Path, fmt: str, sequence: str | None, frames: str | None, depth_from: str = "lidar"
):
    """The reader's validated view of the unpacked run (a KittiSequence or a TumRun);
    InvalidInputError without the staging path if it is unusable or has no frames."""
    try:
        source = open_source(fmt, dataset_root(staging), sequence, frames, depth_from)
    except InvalidInputError as exc:
        message = str(exc).replace(str(staging.resolve()) + "/", "").replace(str(staging), "")
        raise InvalidInputError(f"the uploaded {fmt} run is not usable: {message}") from exc
    if len(source.frames) == 0:
        raise InvalidInputError(f"the uploaded {fmt} run has no frames to use")
    return source


def store_upload(
    state: AppState,
    up: RunUpload,
    archive: UploadFile | None,
    files: list[UploadFile] | None,
    record: RecordRows[T],
) -> tuple[JobRecord, T, Unpacked]:
    """Unpack and validate the upload, let ``record`` store its rows, move the files to
    ``uploads/<job id>``. Blocking: run it in a thread. Nothing stays on any error."""
    with session_scope(state.sessions) as session:
        maps_repo.get_map(session, up.map_id)
    staging = uploads_dir(state.settings) / f"{INCOMING_PREFIX}{uuid.uuid4().hex}"
    final: Path | None = None
    reservation = Reservation(
        upload_space(uploads_dir(state.settings)),
        state.settings.upload_disk_quota_bytes,
        state.settings.uploads_disk_quota_bytes,
    )
    try:
        unpacked = unpack_upload(state, staging, archive, files, reservation)
        source = open_uploaded_run(staging, up.format, up.sequence, up.frames, up.depth_from)
        with session_scope(state.sessions) as session:
            job, extra = record(session, source)
            final = uploads_dir(state.settings) / str(job.id)
            staging.rename(final)
    except BaseException:
        remove_tree(staging)
        if final is not None:
            remove_tree(final)  # renamed, but the transaction did not commit
        raise
    finally:
        reservation.release()  # stored (outside the quota of uploads in flight) or removed
    return job, extra, unpacked

"""A job's uploaded run: unpacked under ``uploads_dir/<job id>`` (default
``data_dir/uploads``, shared by the replicas) by the route that created the job, opened
by the readers from the job's parameters (so a resumed job reads
what the first attempt read), and deleted once the job is done."""

from __future__ import annotations

import shutil
from pathlib import Path

from monoloc.core.errors import InvalidInputError
from monoloc.server.ingest.common import parse_frame_range
from monoloc.server.ingest.sources import read_kitti_sequence, read_tum_run
from monoloc.server.settings import Settings
from monoloc.server.storage.records import JobRecord


def upload_dir_of(job: JobRecord, settings: Settings) -> Path | None:
    """``data_dir/uploads/<job id>`` for jobs that came with an upload, else None."""
    if not job.params.get("upload"):
        return None
    assert settings.uploads_dir is not None
    return Path(settings.uploads_dir) / str(job.id)


def dataset_root(dest: Path) -> Path:
    """``dest``, or the directory it wraps when it holds a single directory and nothing
    else (archives usually contain one top-level folder)."""
    root = dest
    for _ in range(4):
        children = [c for c in root.iterdir() if not c.name.startswith(".")]
        if len(children) != 1 or not children[0].is_dir():
            break
        root = children[0]
    return root


def open_source(
    fmt: str, root: Path, sequence: str | None, frames: str | None, depth_from: str = "lidar"
):
    """The reader's view of an unpacked run: a KittiSequence (its keypoint depth from
    ``depth_from``: lidar or stereo) or a TumRun (validated)."""
    frame_range = parse_frame_range(frames)
    if fmt == "kitti":
        return read_kitti_sequence(
            root, sequence=sequence, frames=frame_range, depth_from=depth_from
        )
    if depth_from != "lidar":
        raise InvalidInputError(
            f"depth_from={depth_from} is for KITTI runs; a TUM run has its depth images"
        )
    if fmt == "tum":
        return read_tum_run(root, frames=frame_range)
    raise InvalidInputError(f"unknown run format {fmt!r}: use kitti or tum")


def remove_tree(path: Path) -> None:
    """Delete an upload directory (missing is fine)."""
    shutil.rmtree(path, ignore_errors=True)


def public_message(text: str, settings: Settings) -> str:
    """An error message without the server's absolute upload paths."""
    uploads = str(Path(settings.uploads_dir or "uploads").resolve()) + "/"
    return text.replace(uploads, "uploads/")

"""Typed operations behind the ``monoloc map ...`` commands (the CLI only parses).

Camera specs (``map create --camera``): ``kitti`` (KITTI odometry camera 0), a TUM
camera name (``freiburg1``, ``freiburg2``, ``freiburg3``, ``default``), a KITTI
``calib.txt`` (image size from the sequence's first image next to it, or
``--width/--height``), a KITTI sequence folder, a TUM run folder or camera JSON, or
none with explicit ``--fx --fy --cx --cy --width --height``.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from monoloc.core.camera import KITTI_CAM0, CameraIntrinsics
from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.formats import kitti, tum
from monoloc.core.formats.png import png_size
from monoloc.core.prior import RetrievalPrior
from monoloc.server.ingest.pipeline import IngestConfig, IngestSummary, ingest_run
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage import runs as runs_repo
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.records import MapRecord, RunRecord, VocabularyRecord


@dataclass(frozen=True)
class CameraOverrides:
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    width_px: int | None = None
    height_px: int | None = None

    def complete(self) -> CameraIntrinsics | None:
        values = (self.fx, self.fy, self.cx, self.cy, self.width_px, self.height_px)
        if all(v is None for v in values):
            return None
        if any(v is None for v in values):
            raise InvalidInputError("give all of --fx --fy --cx --cy --width --height")
        return CameraIntrinsics(*values)  # type: ignore[arg-type]


def _with_size(fx, fy, cx, cy, size: tuple[int, int] | None, o: CameraOverrides, where):
    width = o.width_px or (size[0] if size else None)
    height = o.height_px or (size[1] if size else None)
    if width is None or height is None:
        raise InvalidInputError(f"{where}: image size unknown; give --width and --height")
    return CameraIntrinsics(fx, fy, cx, cy, int(width), int(height))


def camera_from_spec(spec: str | None, overrides: CameraOverrides = CameraOverrides()):
    """A CameraIntrinsics from a camera spec (see the module docstring)."""
    if spec is None:
        camera = overrides.complete()
        if camera is None:
            raise InvalidInputError("give --camera kitti|<calib.txt>|... or --fx ... --height")
        return camera
    if spec.lower() == "kitti":
        return KITTI_CAM0
    if spec.lower() in tum.TUM_CAMERAS:
        return CameraIntrinsics(*tum.TUM_CAMERAS[spec.lower()], 640, 480)
    path = Path(spec).expanduser()
    if path.is_dir() and (path / "calib.txt").is_file():
        path = path / "calib.txt"
    elif path.is_dir():
        return tum.read_run(path).intrinsics
    if not path.is_file():
        raise InvalidInputError(
            f"unknown camera {spec!r}: use kitti, freiburg1|2|3, a calib.txt, a KITTI "
            "sequence folder, a TUM run folder or a camera JSON"
        )
    if path.suffix == ".json":
        try:
            data = json.loads(path.read_text())
            data = {**data, **data.get("camera", {})} if isinstance(data, dict) else {}
            fx, fy, cx, cy = (float(data[k]) for k in ("fx", "fy", "cx", "cy"))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise InputFileError(path, f"needs numeric fx, fy, cx, cy ({exc})") from exc
        w, h = data.get("width_px", data.get("width")), data.get("height_px", data.get("height"))
        return _with_size(fx, fy, cx, cy, (w, h) if w and h else None, overrides, path)
    fx, fy, cx, cy = kitti.read_calib_file(path).pinhole
    first = path.parent / "image_0" / "000000.png"
    size = png_size(first) if first.is_file() else None
    return _with_size(fx, fy, cx, cy, size, overrides, path)


def resolve_vocabulary(session: Session, ref: str = "default") -> VocabularyRecord:
    """``default`` (the shipped vocabulary, stored on first use), an id or a hash."""
    if ref == "default":
        from monoloc.server.vision.vocabulary import load_default_vocabulary

        vocabulary = load_default_vocabulary()
        description = vocabulary.description or "monoloc default vocabulary"
        return maps_repo.get_or_create_vocabulary(session, vocabulary.centres, description)[0]
    if ref.isdigit():
        return maps_repo.get_vocabulary(session, int(ref))
    return maps_repo.get_vocabulary_by_hash(session, ref)


def create_map(
    session_factory: sessionmaker[Session],
    name: str,
    camera: CameraIntrinsics,
    vocabulary: str = "default",
) -> MapRecord:
    with session_scope(session_factory) as session:
        vocab = resolve_vocabulary(session, vocabulary)
        return maps_repo.create_map(session, name, camera, vocab.id)


def find_map(session_factory: sessionmaker[Session], ref: str | int) -> MapRecord:
    with session_scope(session_factory) as session:
        return maps_repo.find_map(session, ref)


def open_source(
    fmt: str,
    path: Path,
    *,
    sequence: str | None = None,
    frames: slice | None = None,
    camera: CameraIntrinsics | None = None,
    tum_camera: str | None = None,
    topics: dict[str, str] | None = None,
    depth_from: str = "lidar",
    map_camera: CameraIntrinsics | None = None,
):
    """Open (and validate) a KITTI sequence, a TUM run or a ROS bag (``topics``: role ->
    topic, see ``monoloc.core.formats.rosbag``; ``map_camera``: the camera of a bag
    without CameraInfo). ``depth_from``: where a KITTI sequence's keypoint depth comes
    from, ``lidar`` (velodyne/) or ``stereo`` (image_1/ and P1), or ``none`` to read its
    images only (a vocabulary's training); a TUM run has its depth camera."""
    if fmt == "kitti":
        from monoloc.server.ingest.sources import read_kitti_sequence

        return read_kitti_sequence(path, sequence, frames, depth_from=depth_from)
    if depth_from not in ("lidar", "none"):
        raise InvalidInputError(
            f"--depth-from {depth_from} is for KITTI sequences; a {fmt} run brings its own "
            "depth (depth images or point clouds)"
        )
    if fmt == "tum":
        from monoloc.server.ingest.sources import read_tum_run

        return read_tum_run(path, intrinsics=camera, camera=tum_camera, frames=frames)
    if fmt == "rosbag":
        from monoloc.server.ingest.sources import read_rosbag_run

        return read_rosbag_run(
            path, topics=topics, intrinsics=camera, fallback_intrinsics=map_camera, frames=frames
        )
    raise InvalidInputError(f"unknown format {fmt!r}: kitti, tum or rosbag")


def ingest_source(
    session_factory: sessionmaker[Session],
    map_ref: str | int,
    source,
    *,
    kind: str = "map",
    tags: tuple[str, ...] = (),
    config: IngestConfig = IngestConfig(),
    registry=None,
    progress: Callable[[int, int], None] | None = None,
) -> IngestSummary:
    """Create a run for ``source`` in the map and ingest it (tags of the run kind added:
    ``night`` for night runs, ``off-center`` for offcenter runs)."""
    record = find_map(session_factory, map_ref)
    with session_scope(session_factory) as session:
        run = runs_repo.create_run(
            session,
            record.id,
            kind=kind,
            source_format=source.format,
            source_name=source.name,
            frames_total=len(source.frames),
        )
    all_tags = runs_repo.tags_for_run(kind, tags)
    return ingest_run(
        session_factory,
        record.id,
        source,
        run_id=run.id,
        registry=registry,
        tags=all_tags,
        progress=progress,
        config=config,
    )


@dataclass(frozen=True)
class MapStats:
    record: MapRecord
    vocabulary: VocabularyRecord
    runs: list[RunRecord]
    tags: dict[str, int]
    points_mean: float
    points_min: int
    points_max: int
    stale_vlads: int  # entries whose VLAD is of another vocabulary than the map's


def map_stats(session_factory: sessionmaker[Session], ref: str | int) -> MapStats:
    from monoloc.server.storage.models import Entry

    with session_scope(session_factory) as session:
        record = maps_repo.find_map(session, ref)
        where = Entry.map_id == record.id
        mean, low, high = session.execute(
            select(
                func.avg(Entry.n_points), func.min(Entry.n_points), func.max(Entry.n_points)
            ).where(where)
        ).one()
        stale = session.scalar(
            select(func.count(Entry.id)).where(where, Entry.vocabulary_id != record.vocabulary_id)
        )
        return MapStats(
            record=record,
            vocabulary=maps_repo.get_vocabulary(session, record.vocabulary_id),
            runs=runs_repo.list_runs(session, record.id),
            tags=entries_repo.tag_counts(session, record.id),
            points_mean=float(mean or 0.0),
            points_min=int(low or 0),
            points_max=int(high or 0),
            stale_vlads=int(stale or 0),
        )


def list_maps(session_factory: sessionmaker[Session]) -> list[MapRecord]:
    with session_scope(session_factory) as session:
        return maps_repo.list_maps(session)


def parse_prior(text: str | None) -> RetrievalPrior | None:
    """``x,y,r`` or ``x,y,r,yaw_deg,tol_deg`` (metres, degrees) -> RetrievalPrior."""
    from monoloc.server.ingest.single import parse_numbers

    if text is None:
        return None
    values = parse_numbers(text, "--prior")
    if len(values) == 3:
        return RetrievalPrior(*values)
    if len(values) == 5:
        return RetrievalPrior(*values[:3], np.deg2rad(values[3]), np.deg2rad(values[4]))
    raise InvalidInputError("--prior takes x,y,r or x,y,r,yaw_deg,tol_deg")

"""Between maps and the formats: import a reader's images as mapping runs, and read a
map's entries as views for a writer."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from monoloc.core.errors import InvalidInputError, NotFoundError
from monoloc.server.formats.model import ImportSource, ModelView
from monoloc.server.ingest.pipeline import IngestConfig, IngestSummary
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.records import MapRecord

_BATCH = 200


def import_sources_into_map(
    session_factory: sessionmaker[Session],
    map_ref: str,
    sources: list[ImportSource],
    *,
    kind: str = "map",
    tags: tuple[str, ...] = (),
    config: IngestConfig = IngestConfig(),
    registry=None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[MapRecord, list[IngestSummary], bool]:
    """Ingest each source (one per camera) as a run of the map, creating the map (default
    vocabulary, the first source's camera) if no map has that name. Idempotent like any
    ingestion. Returns (map, summaries, created).

    All or nothing for a new map: when the import fails, or adds no entry, a map it
    created is deleted again (an empty map is never left behind). An import that adds
    nothing and finds nothing already in the map is an InvalidInputError naming why each
    image was skipped."""
    from monoloc.server.ingest.manage import create_map, find_map, ingest_source

    if not sources:
        raise InvalidInputError("nothing to import: the model has no usable image")
    created = False
    try:
        record = find_map(session_factory, map_ref)
    except NotFoundError:
        record = create_map(session_factory, map_ref, sources[0].intrinsics)
        created = True
    try:
        summaries = [
            ingest_source(
                session_factory,
                record.id,
                source,
                kind=kind,
                tags=tags,
                config=config,
                registry=registry,
                progress=progress,
            )
            for source in sources
        ]
        _check_something_imported(summaries)
    except BaseException:
        if created:
            with session_scope(session_factory) as session:
                maps_repo.delete_map(session, record.id)
        raise
    return find_map(session_factory, record.id), summaries, created


def _check_something_imported(summaries: list[IngestSummary]) -> None:
    if any(s.entries_added or s.skip_reasons.get("already_in_map") for s in summaries):
        return
    reasons: dict[str, int] = {}
    for summary in summaries:
        for reason, n in summary.skip_reasons.items():
            reasons[reason] = reasons.get(reason, 0) + n
    why = ", ".join(f"{n} {reason}" for reason, n in sorted(reasons.items())) or "no image"
    raise InvalidInputError(f"no entry imported (skipped: {why}); the map is unchanged")


def entry_name(entry_id: int) -> str:
    return f"entry_{entry_id:06d}.png"


def map_views(session_factory: sessionmaker[Session], map_ref: str | int):
    """(map, views): every entry of the map as a :class:`ModelView` in the z-up world,
    named ``entry_<id>.png``, with the map's camera; in entry id order."""
    from monoloc.server.ingest.manage import find_map

    record = find_map(session_factory, map_ref)
    views: list[ModelView] = []
    offset = 0
    while True:
        with session_scope(session_factory) as session:
            summaries = entries_repo.list_entries(session, record.id, limit=_BATCH, offset=offset)
            data = entries_repo.get_entry_data(session, [s.id for s in summaries])
        for entry in data:
            T = np.asarray(entry.T_world_from_cam, dtype=np.float64)
            points_world = np.asarray(entry.points_cam, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
            views.append(
                ModelView(
                    name=entry_name(entry.id),
                    intrinsics=record.camera,
                    T_world_from_cam=T,
                    keypoints_px=np.asarray(entry.keypoints_px, dtype=np.float64),
                    points_world=points_world,
                    descriptors=np.asarray(entry.descriptors, dtype=np.uint8),
                    record=entry.id,
                )
            )
        if len(summaries) < _BATCH:
            return record, views
        offset += _BATCH


def _marker(record: MapRecord) -> dict:
    return {
        "written_by": "monoloc",
        "up": "z",
        "world": "monoloc z-up world, metres",
        "map": record.name,
        "map_version": record.version,
    }


def export_map(session_factory: sessionmaker[Session], map_ref: str | int, fmt: str, out_dir):
    """Write the map as a COLMAP model or a kapture dataset; returns (map, entries written)."""
    from pathlib import Path

    from monoloc.core.errors import InvalidInputError

    if fmt not in ("colmap", "kapture"):
        raise InvalidInputError(f"unknown export format {fmt!r}: colmap or kapture")
    record, views = map_views(session_factory, map_ref)
    if fmt == "colmap":
        from monoloc.server.formats.colmap import write_colmap_model

        write_colmap_model(views, Path(out_dir), marker=_marker(record))
    else:
        from monoloc.server.formats.kapture_io import write_kapture_map

        write_kapture_map(views, Path(out_dir), marker=_marker(record))
    return record, len(views)

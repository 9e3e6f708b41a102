"""Between maps and the formats: import a reader's images as mapping runs, and read a
map's entries as views for a writer."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from monoloc.core.camera import CameraIntrinsics
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
    return f"entry_{entry_id:06d}.jpg"


@dataclass(frozen=True)
class TrackMerge:
    """How an export joins the entries' points into multi-view tracks: points of
    different entries whose world positions are within ``radius_m`` and whose ORB
    descriptors differ by at most ``max_hamming`` bits are one 3D point at the mean of
    its members; a track holds at most one keypoint per entry and every member lies
    within ``radius_m`` of the track's point (where a chain of pairs breaks either rule,
    closest pairs are joined first)."""

    radius_m: float = 0.03
    max_hamming: int = 40

    def __post_init__(self) -> None:
        if not self.radius_m >= 0 or not 0 <= self.max_hamming <= 256:
            raise InvalidInputError(f"invalid track merge {self}")


def merge_tracks(
    points_world: list[np.ndarray], descriptors: list[np.ndarray], rule: TrackMerge = TrackMerge()
) -> list[np.ndarray]:
    """Per view the (N,) track id of each of its points (views' points (N, 3) world and
    descriptors (N, 32) uint8), by the ``rule`` (:class:`TrackMerge`). The pairs that
    qualify are joined into connected components at once; only a component that breaks
    a rule is rebuilt greedily, closest pairs first."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    counts = [len(p) for p in points_world]
    n = sum(counts)
    if not n:
        return [np.zeros(0, dtype=np.int64) for _ in counts]
    xyz = np.concatenate([np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in points_world])
    desc = np.concatenate([np.asarray(d, dtype=np.uint8).reshape(-1, 32) for d in descriptors])
    view = np.repeat(np.arange(len(counts)), counts)
    pairs = np.zeros((0, 2), dtype=np.int64)
    if rule.radius_m > 0:
        pairs = cKDTree(xyz).query_pairs(rule.radius_m, output_type="ndarray").astype(np.int64)
        pairs = pairs[view[pairs[:, 0]] != view[pairs[:, 1]]]
        bits = np.unpackbits(desc[pairs[:, 0]] ^ desc[pairs[:, 1]], axis=1).sum(axis=1)
        pairs = pairs[bits <= rule.max_hamming]
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    n_labels, labels = connected_components(graph, directed=False)
    labels = labels.astype(np.int64)
    # components to rebuild: one view twice, or a member beyond the radius of the mean
    order = np.lexsort((view, labels))
    twice = (labels[order][1:] == labels[order][:-1]) & (view[order][1:] == view[order][:-1])
    bad = np.zeros(n_labels, dtype=bool)
    bad[labels[order][1:][twice]] = True
    size = np.bincount(labels, minlength=n_labels)
    mean = np.stack([np.bincount(labels, xyz[:, k], n_labels) for k in range(3)], 1)
    mean /= size[:, None]
    bad[labels[np.linalg.norm(xyz - mean[labels], axis=1) > rule.radius_m]] = True
    if bad.any():
        redo = pairs[bad[labels[pairs[:, 0]]]]
        distance = np.linalg.norm(xyz[redo[:, 0]] - xyz[redo[:, 1]], axis=1)
        parent: dict[int, int] = {}
        members: dict[int, list[int]] = {}

        def root(i: int) -> int:
            while parent.get(i, i) != i:
                i = parent[i]
            return i

        for a, b in redo[np.argsort(distance, kind="stable")].tolist():
            ra, rb = root(a), root(b)
            if ra == rb:
                continue
            joined = members.get(ra, [ra]) + members.get(rb, [rb])
            if len(set(view[joined].tolist())) < len(joined):
                continue  # a track holds one keypoint per view
            spread = np.linalg.norm(xyz[joined] - xyz[joined].mean(axis=0), axis=1).max()
            if spread > rule.radius_m:
                continue  # every member stays within the radius of the track's point
            parent[rb] = ra
            members[ra] = joined
            members.pop(rb, None)
        in_bad = np.flatnonzero(bad[labels])
        labels[in_bad] = n_labels + np.array([root(int(i)) for i in in_bad], dtype=np.int64)
    _, ids = np.unique(labels, return_inverse=True)
    return np.split(ids.astype(np.int64), np.cumsum(counts)[:-1])


def _preview_camera(camera: CameraIntrinsics, width_px: int, height_px: int) -> CameraIntrinsics:
    """The map's camera for its image resized to width x height (pixel centres kept)."""
    sx, sy = width_px / camera.width_px, height_px / camera.height_px
    return CameraIntrinsics(
        camera.fx * sx,
        camera.fy * sy,
        (camera.cx + 0.5) * sx - 0.5,
        (camera.cy + 0.5) * sy - 0.5,
        width_px,
        height_px,
        camera.distortion,
    )


def map_views(
    session_factory: sessionmaker[Session], map_ref: str | int, merge: TrackMerge = TrackMerge()
):
    """(map, views): every entry of the map as a :class:`ModelView` in the z-up world,
    named ``entry_<id>.jpg``, in entry id order, with its stored image (the preview JPEG,
    at most 640 px; the server keeps no full-size image) and the map's camera scaled to
    it, its keypoints scaled likewise, and its points joined into multi-view tracks
    (``merge``; each keypoint takes its track's mean position). An entry without a stored
    image is exported at the camera's size without an image file."""
    from monoloc.server.ingest.manage import find_map

    record = find_map(session_factory, map_ref)
    entries, images = [], []
    offset = 0
    while True:
        with session_scope(session_factory) as session:
            summaries = entries_repo.list_entries(session, record.id, limit=_BATCH, offset=offset)
            data = entries_repo.get_entry_data(session, [s.id for s in summaries])
            for entry in data:
                entries.append(entry)
                images.append(entries_repo.get_entry_image(session, entry.id))
        if len(summaries) < _BATCH:
            break
        offset += _BATCH
    camera = record.camera
    worlds = []
    for entry in entries:
        size = (entry.summary.image_width_px, entry.summary.image_height_px)
        if size != (camera.width_px, camera.height_px):
            raise InvalidInputError(
                f"entry {entry.id} is {size[0]}x{size[1]} but map {record.name}'s camera is "
                f"{camera.width_px}x{camera.height_px}: its intrinsics are not known"
            )
        T = np.asarray(entry.T_world_from_cam, dtype=np.float64)
        worlds.append(np.asarray(entry.points_cam, dtype=np.float64) @ T[:3, :3].T + T[:3, 3])
    track_ids = merge_tracks(worlds, [e.descriptors for e in entries], merge)
    views: list[ModelView] = []
    for entry, image, world, ids in zip(entries, images, worlds, track_ids, strict=True):
        keypoints = np.asarray(entry.keypoints_px, dtype=np.float64).reshape(-1, 2)
        intrinsics, image_bytes = camera, None
        if image is not None:
            intrinsics = _preview_camera(camera, image.width_px, image.height_px)
            scale = np.array([intrinsics.fx / camera.fx, intrinsics.fy / camera.fy])
            keypoints = (keypoints + 0.5) * scale - 0.5
            image_bytes = image.jpeg
        views.append(
            ModelView(
                name=entry_name(entry.id),
                intrinsics=intrinsics,
                T_world_from_cam=np.asarray(entry.T_world_from_cam, dtype=np.float64),
                keypoints_px=keypoints,
                points_world=world,
                descriptors=np.asarray(entry.descriptors, dtype=np.uint8),
                record=entry.id,
                point_ids=ids,
                image_bytes=image_bytes,
            )
        )
    return record, views


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

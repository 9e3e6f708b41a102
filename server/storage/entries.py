"""Repository of map entries: idempotent add, delete, tags, filtered listing, arrays.

Every add, delete or VLAD rewrite bumps the map's version in the same transaction, so an
index stamped with an older version is known to be stale. Functions never commit.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence

import numpy as np
from sqlalchemy import Select, delete, exists, func, insert, or_, select, update
from sqlalchemy.orm import Session, selectinload, undefer

from monoloc.core.errors import InvalidInputError, NotFoundError
from monoloc.server.storage import arrays as arr
from monoloc.server.storage._sql import insert_or_ignore
from monoloc.server.storage.entry_checks import (
    check_area,
    check_code_and_vlad,
    check_new_entry,
    check_source_hash,
    normalise_tags,
)
from monoloc.server.storage.maps import bump_map_version, get_vocabulary
from monoloc.server.storage.models import Entry, EntryImage, EntryTag, Map, Run, utc_now
from monoloc.server.storage.records import (
    Area,
    EntryData,
    EntryImageData,
    EntrySummary,
    MapVectors,
    NewEntry,
)

_IN_CHUNK = 500  # ids/hashes per IN (...) clause


def _summary(row: Entry) -> EntrySummary:
    return EntrySummary(
        id=row.id,
        map_id=row.map_id,
        run_id=row.run_id,
        source_image_hash=row.source_image_hash,
        x_m=row.x_m,
        y_m=row.y_m,
        yaw_rad=row.yaw_rad,
        tags=tuple(t.tag for t in row.tags),
        vocabulary_id=row.vocabulary_id,
        n_points=row.n_points,
        image_width_px=row.image_width_px,
        image_height_px=row.image_height_px,
        timestamp_s=row.timestamp_s,
        created_at=row.created_at,
    )


def _load(session: Session, entry_id: int, map_id: int | None) -> Entry:
    stmt = (
        select(Entry)
        .where(Entry.id == entry_id)
        .options(selectinload(Entry.tags))
        .execution_options(populate_existing=True)
    )
    row = session.scalars(stmt).first()
    if row is None or (map_id is not None and row.map_id != map_id):
        where = "" if map_id is None else f" in map {map_id}"
        raise NotFoundError(f"entry {entry_id} does not exist{where}")
    return row


def add_entry(
    session: Session,
    map_id: int,
    entry: NewEntry,
    *,
    run_id: int | None = None,
    also_known_as: Iterable[str] = (),
) -> tuple[EntrySummary, bool]:
    """Add ``entry`` to the map unless one with the same source image hash is there
    (or one stored under a hash of ``also_known_as``: the same image's older identity).

    Returns (summary, created). A new entry bumps the map version in the same transaction;
    an existing one is returned untouched (even if another transaction inserted it
    concurrently: no error, no duplicate).
    """
    source_hash = check_source_hash(entry.source_image_hash)
    known = sorted({source_hash, *(check_source_hash(h) for h in also_known_as)})
    existing = session.scalars(
        select(Entry.id)
        .where(Entry.map_id == map_id, Entry.source_image_hash.in_(known))
        .order_by(Entry.id)
    ).first()
    if existing is not None:
        return _summary(_load(session, existing, None)), False
    map_row = session.get(Map, map_id, populate_existing=True)
    if map_row is None:
        raise NotFoundError(f"map {map_id} does not exist")
    if run_id is not None:
        run_map = session.scalars(select(Run.map_id).where(Run.id == run_id)).first()
        if run_map != map_id:
            raise InvalidInputError(f"run {run_id} does not exist in map {map_id}")
    vocabulary_id = entry.vocabulary_id or map_row.vocabulary_id
    if entry.vocabulary_id is not None:
        get_vocabulary(session, vocabulary_id)
    values = check_new_entry(entry, source_hash)
    image_values = None if entry.image is None else _check_image(entry.image, values)
    values.update(map_id=map_id, run_id=run_id, vocabulary_id=vocabulary_id, created_at=utc_now())
    new_id = insert_or_ignore(session, Entry, values, ["map_id", "source_image_hash"])
    if new_id is None:  # inserted by a concurrent transaction since our first look
        existing = session.scalars(
            select(Entry.id).where(Entry.map_id == map_id, Entry.source_image_hash == source_hash)
        ).one()
        return _summary(_load(session, existing, None)), False
    tags = normalise_tags(entry.tags)
    if tags:
        session.execute(insert(EntryTag), [{"entry_id": new_id, "tag": t} for t in tags])
    if entry.image is not None:
        session.execute(insert(EntryImage), [{"entry_id": new_id, **image_values}])
    bump_map_version(session, map_id, "add", new_id)
    return _summary(_load(session, new_id, None)), True


_JPEG_MAGIC = b"\xff\xd8\xff"


def _check_image(image: EntryImageData, entry_values: dict) -> dict:
    """Column values of an entry's image row; InvalidInputError if it is not a JPEG no
    larger than the entry's image, or its keypoints are not (M, 2) finite pixels."""
    width, height = int(image.width_px), int(image.height_px)
    full_w, full_h = entry_values["image_width_px"], entry_values["image_height_px"]
    if not (0 < width <= full_w and 0 < height <= full_h):
        raise InvalidInputError(
            f"entry image is {width}x{height}; it must be within the {full_w}x{full_h} image"
        )
    if not bytes(image.jpeg[:3]) == _JPEG_MAGIC:
        raise InvalidInputError("entry image must be a JPEG")
    keypoints = arr.pack_array(
        image.keypoints_without_point_px, arr.KEYPOINTS, "keypoints_without_point_px"
    )
    return dict(
        jpeg=bytes(image.jpeg),
        width_px=width,
        height_px=height,
        keypoints_without_point_px=keypoints,
    )


def get_entry_image(
    session: Session, entry_id: int, *, map_id: int | None = None
) -> EntryImageData | None:
    """The entry's stored image, None if it has none (added before images were kept);
    NotFoundError if the entry does not exist (or is not in ``map_id``)."""
    _load(session, entry_id, map_id)
    row = session.get(EntryImage, entry_id)
    if row is None:
        return None
    return EntryImageData(
        jpeg=row.jpeg,
        width_px=row.width_px,
        height_px=row.height_px,
        keypoints_without_point_px=arr.unpack_array(
            row.keypoints_without_point_px, arr.KEYPOINTS, "keypoints_without_point_px"
        ),
    )


def get_entry(session: Session, entry_id: int, *, map_id: int | None = None) -> EntrySummary:
    """An entry's summary; NotFoundError if it does not exist (or is not in ``map_id``)."""
    return _summary(_load(session, entry_id, map_id))


def delete_entry(session: Session, entry_id: int, *, map_id: int | None = None) -> int:
    """Delete an entry (its tags cascade) and bump its map's version; returns the version."""
    row = _load(session, entry_id, map_id)
    owner = row.map_id
    session.expunge(row)
    session.execute(
        delete(Entry).where(Entry.id == entry_id).execution_options(synchronize_session=False)
    )
    return bump_map_version(session, owner, "delete", entry_id)


def set_entry_tags(
    session: Session, entry_id: int, tags: Iterable[str], *, map_id: int | None = None
) -> EntrySummary:
    """Replace the entry's tags (normalised to lower case, duplicates dropped); bumps the
    map version (replicas re-read the entry's tags)."""
    row = _load(session, entry_id, map_id)
    clean = normalise_tags(tags)
    session.execute(delete(EntryTag).where(EntryTag.entry_id == entry_id))
    if clean:
        session.execute(insert(EntryTag), [{"entry_id": entry_id, "tag": t} for t in clean])
    bump_map_version(session, row.map_id, "retag", entry_id)
    return _summary(_load(session, entry_id, map_id))


def _filtered(
    stmt: Select, map_id: int, tag: str | None, run_id: int | None, area: Area | None
) -> Select:
    stmt = stmt.where(Entry.map_id == map_id)
    if tag is not None:
        (clean,) = normalise_tags([tag])
        stmt = stmt.where(exists().where(EntryTag.entry_id == Entry.id, EntryTag.tag == clean))
    if run_id is not None:
        stmt = stmt.where(Entry.run_id == run_id)
    if area is not None:
        x, y, r = check_area(area)
        # Bounding box first (uses the (map_id, x_m, y_m) index), then the exact disc.
        stmt = stmt.where(
            Entry.x_m.between(x - r, x + r),
            Entry.y_m.between(y - r, y + r),
            (Entry.x_m - x) * (Entry.x_m - x) + (Entry.y_m - y) * (Entry.y_m - y) <= r * r,
        )
    return stmt


def list_entries(
    session: Session,
    map_id: int,
    *,
    tag: str | None = None,
    run_id: int | None = None,
    area: Area | None = None,
    limit: int = 100,
    offset: int = 0,
) -> list[EntrySummary]:
    """Entries of a map in id order, filtered by tag, run and/or area (a disc)."""
    if limit < 0 or offset < 0:
        raise InvalidInputError(f"limit and offset must be >= 0, got {limit}, {offset}")
    stmt = _filtered(select(Entry), map_id, tag, run_id, area)
    stmt = stmt.options(selectinload(Entry.tags)).order_by(Entry.id).limit(limit).offset(offset)
    return [_summary(row) for row in session.scalars(stmt)]


def count_entries(
    session: Session,
    map_id: int,
    *,
    tag: str | None = None,
    run_id: int | None = None,
    area: Area | None = None,
) -> int:
    """How many entries ``list_entries`` would return without limit/offset."""
    stmt = _filtered(select(func.count(Entry.id)), map_id, tag, run_id, area)
    return int(session.scalar(stmt) or 0)


def tag_counts(session: Session, map_id: int) -> dict[str, int]:
    """Number of entries per tag in a map."""
    stmt = (
        select(EntryTag.tag, func.count())
        .join(Entry, Entry.id == EntryTag.entry_id)
        .where(Entry.map_id == map_id)
        .group_by(EntryTag.tag)
        .order_by(EntryTag.tag)
    )
    return {tag: int(n) for tag, n in session.execute(stmt)}


def existing_hashes(session: Session, map_id: int, hashes: Iterable[str]) -> set[str]:
    """The subset of ``hashes`` already in the map (lets a resumed ingestion skip frames)."""
    wanted = sorted({check_source_hash(h) for h in hashes})
    found: set[str] = set()
    for i in range(0, len(wanted), _IN_CHUNK):
        chunk = wanted[i : i + _IN_CHUNK]
        stmt = select(Entry.source_image_hash).where(
            Entry.map_id == map_id, Entry.source_image_hash.in_(chunk)
        )
        found.update(session.scalars(stmt))
    return found


def runs_of_hashes(session: Session, map_id: int, hashes: Iterable[str]) -> dict[str, int | None]:
    """For each of ``hashes`` already in the map, the run its entry belongs to (None: an
    entry added on its own); lets a resumed ingestion tell its own entries from others."""
    wanted = sorted({check_source_hash(h) for h in hashes})
    found: dict[str, int | None] = {}
    for i in range(0, len(wanted), _IN_CHUNK):
        chunk = wanted[i : i + _IN_CHUNK]
        stmt = select(Entry.source_image_hash, Entry.run_id).where(
            Entry.map_id == map_id, Entry.source_image_hash.in_(chunk)
        )
        found.update((h, r) for h, r in session.execute(stmt))
    return found


def _data(row: Entry) -> EntryData:
    where = f"entries id={row.id}"
    return EntryData(
        summary=_summary(row),
        T_world_from_cam=arr.unpack_array(
            row.T_world_from_cam, arr.POSE, f"{where} T_world_from_cam"
        ),
        vlad=arr.unpack_array(row.vlad, arr.VLAD, f"{where} vlad"),
        code=arr.unpack_array(row.code, arr.CODE, f"{where} code"),
        keypoints_px=arr.unpack_array(row.keypoints_px, arr.KEYPOINTS, f"{where} keypoints_px"),
        descriptors=arr.unpack_array(row.descriptors, arr.DESCRIPTORS, f"{where} descriptors"),
        points_cam=arr.unpack_array(row.points_cam, arr.POINTS, f"{where} points_cam"),
    )


def get_entry_data(session: Session, entry_ids: Sequence[int]) -> list[EntryData]:
    """Entries with their arrays, in the order of ``entry_ids``; NotFoundError if any is
    missing, InvalidInputError if a stored blob is corrupt."""
    rows: dict[int, Entry] = {}
    unique_ids = list(dict.fromkeys(int(i) for i in entry_ids))
    for i in range(0, len(unique_ids), _IN_CHUNK):
        stmt = (
            select(Entry)
            .where(Entry.id.in_(unique_ids[i : i + _IN_CHUNK]))
            .options(undefer("*"), selectinload(Entry.tags))
            .execution_options(populate_existing=True)
        )
        rows.update((row.id, row) for row in session.scalars(stmt))
    missing = [i for i in unique_ids if i not in rows]
    if missing:
        raise NotFoundError(f"entries {missing[:10]} do not exist")
    return [_data(rows[int(i)]) for i in entry_ids]


def existing_entry_data(session: Session, entry_ids: Sequence[int]) -> list[EntryData]:
    """Like :func:`get_entry_data`, without those of ``entry_ids`` that no longer exist
    (an index may still list an entry deleted a moment ago)."""
    try:
        return get_entry_data(session, entry_ids)
    except NotFoundError:
        rows = []
        for entry_id in entry_ids:
            try:
                rows.extend(get_entry_data(session, [entry_id]))
            except NotFoundError:
                continue
        return rows


def _vectors(rows) -> MapVectors:
    ids = np.array([r[0] for r in rows], dtype=np.int64)
    if not len(ids):
        return MapVectors(
            entry_ids=ids,
            vlads=np.zeros((0, arr.VLAD[1][0]), np.float32),
            codes=np.zeros((0, arr.CODE[1][0]), np.uint8),
            planar=np.zeros((0, 3), np.float64),
        )
    vlads = np.stack([arr.unpack_array(r[1], arr.VLAD, f"entries id={r[0]} vlad") for r in rows])
    codes = np.stack([arr.unpack_array(r[2], arr.CODE, f"entries id={r[0]} code") for r in rows])
    planar = np.array([(r[3], r[4], r[5]) for r in rows], dtype=np.float64)
    return MapVectors(entry_ids=ids, vlads=vlads, codes=codes, planar=planar)


_VECTOR_COLUMNS = (Entry.id, Entry.vlad, Entry.code, Entry.x_m, Entry.y_m, Entry.yaw_rad)


def iter_map_vectors(
    session: Session,
    map_id: int,
    *,
    batch_size: int = 4096,
    exclude_run_id: int | None = None,
    within_m: tuple[float, float, float, float] | None = None,
) -> Iterator[MapVectors]:
    """All of a map's (entry id, VLAD, code, planar pose) in id order, in batches, for
    building a retrieval index; without the entries of run ``exclude_run_id`` and only
    those inside the world box ``within_m`` = (x_min, x_max, y_min, y_max) if given.
    Corrupt blobs raise InvalidInputError."""
    where = [Entry.map_id == map_id]
    if exclude_run_id is not None:
        where.append(or_(Entry.run_id.is_(None), Entry.run_id != exclude_run_id))
    if within_m is not None:
        x_min, x_max, y_min, y_max = within_m
        where += [Entry.x_m.between(x_min, x_max), Entry.y_m.between(y_min, y_max)]
    stmt = (
        select(*_VECTOR_COLUMNS)
        .where(*where)
        .order_by(Entry.id)
        .execution_options(yield_per=batch_size)
    )
    for part in session.execute(stmt).partitions():
        yield _vectors(part)


def map_vectors_of(session: Session, map_id: int, entry_ids: Sequence[int]) -> MapVectors:
    """The retrieval data of those of ``entry_ids`` that exist in the map, in id order
    (a replica applying the change log)."""
    rows = []
    unique_ids = sorted({int(i) for i in entry_ids})
    for i in range(0, len(unique_ids), _IN_CHUNK):
        stmt = select(*_VECTOR_COLUMNS).where(
            Entry.map_id == map_id, Entry.id.in_(unique_ids[i : i + _IN_CHUNK])
        )
        rows.extend(session.execute(stmt))
    rows.sort(key=lambda r: r[0])
    return _vectors(rows)


def update_entry_vlad(
    session: Session, entry_id: int, *, vlad: np.ndarray, code: np.ndarray, vocabulary_id: int
) -> int:
    """Replace an entry's VLAD and code (after a vocabulary change); bumps the map version
    and returns it."""
    row = _load(session, entry_id, None)
    get_vocabulary(session, vocabulary_id)
    vlad_blob, code_blob = check_code_and_vlad(vlad, code, f"entry {entry_id}")
    session.execute(
        update(Entry)
        .where(Entry.id == entry_id)
        .values(vlad=vlad_blob, code=code_blob, vocabulary_id=vocabulary_id)
        .execution_options(synchronize_session=False)
    )
    return bump_map_version(session, row.map_id, "vlad", entry_id)

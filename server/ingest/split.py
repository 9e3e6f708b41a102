"""Splitting a map into shard groups (``monoloc shards split``): the entries of one
group's tiles copied from the map's database into the group's own database.

The group's copy is a map of the tile table's name holding everything a replica needs to
serve it: the map's header (its camera, corner rule, geo-reference, measurement-model
calibration), the vocabularies its entries were computed with, the runs that own copied
entries (their records as the source holds them, so the console can tell routes apart),
and each entry of the group's tiles with its arrays, tags and console image. Left behind:
API keys (each group has its own ``api_keys``: create the vehicle's key in each), the
vehicles' registered cameras (they belong to keys; a vehicle registers with each group),
jobs (a process's history), the change log (the copy writes its own) and the entries of
other tiles.

Tile membership is ``TileScheme.tile_of`` of the entry's stored position, the rule
``monoloc shards coverage`` checks. Entries are written ``batch_rows`` per transaction
keeping the map's invariants as ``entries.add_entry`` does: every row passes
``check_new_entry``, the map version rises by one per entry with one ``add`` row in the
change log each, under the map's write lock. An entry is known by its source image hash,
so a rerun after an interruption copies only what is missing, and a rerun on a complete
copy copies nothing.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass

from sqlalchemy import func, insert, select, update
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

from monoloc.core.errors import ConflictError, InvalidInputError, NotFoundError
from monoloc.core.tiles import TileTable
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage.db import (
    create_engine_for_url,
    libpq_params,
    make_session_factory,
    redact_url,
    session_scope,
)
from monoloc.server.storage.entry_checks import check_new_entry, normalise_tags
from monoloc.server.storage.models import (
    Entry,
    EntryImage,
    EntryTag,
    Map,
    MapChange,
    Run,
    utc_now,
)
from monoloc.server.storage.records import EntryData, MapRecord, NewEntry

DEFAULT_BATCH_ROWS = 1000  # ~25 MB of entry rows in memory per transaction


@dataclass(frozen=True)
class SplitSummary:
    """What a split did: ``in_group`` entries of the source map lie in the group's tiles,
    ``copied`` of them were written now, ``already_there`` were in the destination
    before, ``outside`` lie in other groups' tiles or in none; ``runs_copied`` run
    records and ``vocabularies_copied`` vocabularies were added; ``calibration`` is
    "copied", "kept the destination's" or "none"."""

    map_name: str
    map_id: int  # in the destination
    created: bool
    in_group: int
    copied: int
    already_there: int
    outside: int
    runs_copied: int
    vocabularies_copied: int
    calibration: str
    seconds: float
    version: int


@dataclass(frozen=True)
class SplitPlan:
    """The source map and, in id order, (entry id, source image hash) of each of its
    entries in the group's tiles; ``n_entries`` of the whole source map."""

    table: TileTable
    group: str
    source: MapRecord
    rows: list[tuple[int, str]]
    n_entries: int


def same_database(url_a: str, url_b: str) -> bool:
    """Whether two SQLAlchemy URLs name the same database: the same SQLite file (after
    resolving the path), or the same PostgreSQL hosts, ports and database name."""
    a, b = make_url(url_a), make_url(url_b)
    if a.get_backend_name() != b.get_backend_name():
        return False
    if a.get_backend_name() == "sqlite":
        files = [u.database for u in (a, b)]
        if any(not f or f == ":memory:" for f in files):
            return False
        return os.path.realpath(files[0]) == os.path.realpath(files[1])
    if a.get_backend_name() == "postgresql":
        keys = ("host", "port", "dbname")
        pa, pb = libpq_params(url_a), libpq_params(url_b)
        return all(str(pa.get(k) or "") == str(pb.get(k) or "") for k in keys)
    return a.set(password=None, username=None) == b.set(password=None, username=None)


def plan_split(session: Session, table: TileTable, group: str) -> SplitPlan:
    """The source map's entries in ``group``'s tiles (read from the (map_id, x_m, y_m)
    index tile by tile, each position tested with ``TileScheme.tile_of``)."""
    if group not in table.groups:
        raise InvalidInputError(f"group {group!r} is not in the tile table")
    try:
        source = maps_repo.get_map_by_name(session, table.map_name)
    except NotFoundError:
        raise NotFoundError(f"map {table.map_name!r} is not in the source database") from None
    scheme = table.scheme
    # a margin around each tile's box: the box only narrows the search, tile_of decides
    margin_m = 1e-6 * scheme.size_m
    rows: dict[int, str] = {}
    for tile in table.tiles_of(group):
        x0, y0, x1, y1 = scheme.bounds(tile)
        found = session.execute(
            select(Entry.id, Entry.source_image_hash, Entry.x_m, Entry.y_m).where(
                Entry.map_id == source.id,
                Entry.x_m.between(x0 - margin_m, x1 + margin_m),
                Entry.y_m.between(y0 - margin_m, y1 + margin_m),
            )
        )
        for entry_id, source_hash, x_m, y_m in found:
            if scheme.tile_of(float(x_m), float(y_m)) == tile:
                rows[int(entry_id)] = source_hash
    return SplitPlan(table, group, source, sorted(rows.items()), source.n_entries)


def _check_compatible(dest: MapRecord, source: MapRecord) -> None:
    """ConflictError when the destination's map of the same name is another map (a
    destination without a geo-reference is given the source's)."""
    differences = [
        ("vocabulary", dest.vocabulary_hash, source.vocabulary_hash),
        ("camera", dest.camera, source.camera),
        ("corner rule", dest.features or {}, source.features or {}),
    ]
    if dest.geo_reference is not None:
        differences.append(("geo-reference", dest.geo_reference, source.geo_reference))
    for what, theirs, ours in differences:
        if theirs != ours:
            raise ConflictError(
                f"the destination's map {dest.name!r} has another {what} than the source's "
                f"({theirs} vs {ours}): not a copy of the same map"
            )


@dataclass(frozen=True)
class _Destination:
    record: MapRecord
    created: bool
    vocabulary_ids: dict[int, int]  # source vocabulary id -> destination's
    run_ids: dict[int, int]  # source run id -> destination's
    runs_copied: int
    vocabularies_copied: int
    calibration: str


def _run_key(row: Run) -> tuple:
    return (row.kind, row.source_format, row.source_name, row.created_at)


def _prepare_destination(
    source_session: Session, dest_session: Session, plan: SplitPlan
) -> _Destination:
    """In one transaction of ``dest_session``: the vocabularies, the map (created if
    absent, else checked), its calibration when it has none, and the runs owning the
    plan's entries (a run already copied is found again by kind, format, name and
    creation time)."""
    source = plan.source
    vocabulary_ids: dict[int, int] = {}
    vocabularies_copied = 0
    used = set(
        source_session.scalars(
            select(Entry.vocabulary_id).where(Entry.map_id == source.id).distinct()
        )
    )
    for vocabulary_id in sorted(used | {source.vocabulary_id}):
        vocab = maps_repo.get_vocabulary(source_session, vocabulary_id)
        copy, created = maps_repo.get_or_create_vocabulary(
            dest_session, vocab.centres, vocab.description
        )
        if copy.version_hash != vocab.version_hash:
            raise InvalidInputError(
                f"vocabulary {vocab.version_hash[:12]} hashes to {copy.version_hash[:12]} "
                "when copied"
            )
        vocabulary_ids[vocabulary_id] = copy.id
        vocabularies_copied += int(created)

    try:
        dest = maps_repo.get_map_by_name(dest_session, source.name)
        created = False
        _check_compatible(dest, source)
    except NotFoundError:
        dest = maps_repo.create_map(
            dest_session,
            source.name,
            source.camera,
            vocabulary_ids[source.vocabulary_id],
            features=source.features or {},
        )
        created = True
    if dest.geo_reference is None and source.geo_reference is not None:
        maps_repo.set_geo_reference(dest_session, dest.id, source.geo_reference)
    calibration = "none"
    if source.calibration is not None:
        if dest.calibration is None:
            maps_repo.set_calibration(dest_session, dest.id, source.calibration)
            calibration = "copied"
        elif dest.calibration != source.calibration:
            calibration = "kept the destination's"
        else:
            calibration = "copied"

    run_ids, runs_copied = _copy_runs(source_session, dest_session, plan, dest.id)
    return _Destination(
        maps_repo.get_map(dest_session, dest.id),
        created,
        vocabulary_ids,
        run_ids,
        runs_copied,
        vocabularies_copied,
        calibration,
    )


def _copy_runs(
    source_session: Session, dest_session: Session, plan: SplitPlan, dest_map_id: int
) -> tuple[dict[int, int], int]:
    """Source run id -> destination run id of the runs owning the plan's entries (their
    rows copied as they are, counters of the whole run); and how many were added."""
    ids = [entry_id for entry_id, _ in plan.rows]
    owners: set[int] = set()
    for start in range(0, len(ids), 500):
        owners.update(
            source_session.scalars(
                select(Entry.run_id)
                .where(Entry.id.in_(ids[start : start + 500]), Entry.run_id.is_not(None))
                .distinct()
            )
        )
    if not owners:
        return {}, 0
    existing = {
        _run_key(row): row.id
        for row in dest_session.scalars(select(Run).where(Run.map_id == dest_map_id))
    }
    columns = [c.key for c in Run.__table__.columns if c.key not in ("id", "map_id")]
    mapping, added = {}, 0
    for row in source_session.scalars(select(Run).where(Run.id.in_(sorted(owners)))):
        key = _run_key(row)
        if key not in existing:
            values = {c: getattr(row, c) for c in columns}
            existing[key] = dest_session.scalar(
                insert(Run).values(map_id=dest_map_id, **values).returning(Run.id)
            )
            added += 1
        mapping[row.id] = int(existing[key])
    return mapping, added


def _new_entry(data: EntryData) -> NewEntry:
    s = data.summary
    return NewEntry(
        source_image_hash=s.source_image_hash,
        T_world_from_cam=data.T_world_from_cam,
        vlad=data.vlad,
        code=data.code,
        keypoints_px=data.keypoints_px,
        descriptors=data.descriptors,
        points_cam=data.points_cam,
        image_width_px=s.image_width_px,
        image_height_px=s.image_height_px,
        tags=s.tags,
        timestamp_s=s.timestamp_s,
    )


def _write_batch(
    session: Session,
    dest: _Destination,
    plan: SplitPlan,
    data: list[EntryData],
    images: dict[int, dict],
) -> int:
    """Insert the entries of ``data`` the destination map does not hold yet (with their
    tags and images), one version and one ``add`` change each; returns how many. Does
    not commit."""
    map_id = dest.record.id
    # A write first: it takes the map's write lock (SQLite: the database's), so that no
    # other writer adds one of these hashes between the look and the insert.
    session.execute(
        update(Map)
        .where(Map.id == map_id)
        .values(version=Map.version)
        .execution_options(synchronize_session=False)
    )
    known = entries_repo.existing_hashes(
        session, map_id, [d.summary.source_image_hash for d in data]
    )
    fresh = [d for d in data if d.summary.source_image_hash not in known]
    if not fresh:
        return 0
    scheme, tiles = plan.table.scheme, set(plan.table.tiles_of(plan.group))
    rows, tags, entry_images = [], [], []
    for d in fresh:
        values = check_new_entry(_new_entry(d), d.summary.source_image_hash)
        if scheme.tile_of(values["x_m"], values["y_m"]) not in tiles:
            raise InvalidInputError(
                f"source entry {d.id}: its pose puts it at ({values['x_m']:.3f}, "
                f"{values['y_m']:.3f}), outside the tiles its stored position lies in"
            )
        run_id = d.summary.run_id
        values.update(
            map_id=map_id,
            run_id=None if run_id is None else dest.run_ids[run_id],
            vocabulary_id=dest.vocabulary_ids[d.summary.vocabulary_id],
            created_at=d.summary.created_at,
        )
        rows.append(values)
    version = session.execute(
        update(Map)
        .where(Map.id == map_id)
        .values(version=Map.version + len(fresh), updated_at=utc_now())
        .returning(Map.version)
        .execution_options(synchronize_session=False)
    ).scalar_one()
    ids = session.scalars(
        insert(Entry).returning(Entry.id, sort_by_parameter_order=True), rows
    ).all()
    for d, new_id in zip(fresh, ids, strict=True):
        tags += [{"entry_id": new_id, "tag": t} for t in normalise_tags(d.summary.tags)]
        if d.id in images:
            entry_images.append({**images[d.id], "entry_id": new_id})
    if tags:
        session.execute(insert(EntryTag), tags)
    if entry_images:
        session.execute(insert(EntryImage), entry_images)
    first_version, now = int(version) - len(fresh) + 1, utc_now()
    session.execute(
        insert(MapChange),
        [
            dict(
                map_id=map_id,
                version=first_version + i,
                kind="add",
                entry_id=int(new_id),
                created_at=now,
            )
            for i, new_id in enumerate(ids)
        ],
    )
    if session.get_bind().dialect.name == "postgresql":
        channel = maps_repo.CHANGES_CHANNEL
        session.execute(select(func.pg_notify(channel, f"{map_id}:{int(version)}")))
    return len(fresh)


def _source_images(session: Session, entry_ids: list[int]) -> dict[int, dict]:
    """The console images of ``entry_ids`` as stored (they were checked when written and
    are read by people, not by localization): entry id -> column values."""
    out = {}
    for start in range(0, len(entry_ids), 500):
        for row in session.scalars(
            select(EntryImage).where(EntryImage.entry_id.in_(entry_ids[start : start + 500]))
        ):
            out[row.entry_id] = dict(
                jpeg=row.jpeg,
                width_px=row.width_px,
                height_px=row.height_px,
                keypoints_without_point_px=row.keypoints_without_point_px,
            )
    return out


def copy_entries(
    source_factory: sessionmaker[Session],
    dest_factory: sessionmaker[Session],
    plan: SplitPlan,
    dest: _Destination,
    batch_rows: int,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[int, int]:
    """Copy the plan's entries missing in the destination, ``batch_rows`` per
    transaction (``progress(done, total)`` after each); (copied, already there)."""
    copied = already = 0
    for start in range(0, len(plan.rows), batch_rows):
        part = plan.rows[start : start + batch_rows]
        with dest_factory() as session:
            known = entries_repo.existing_hashes(session, dest.record.id, [h for _, h in part])
        missing = [entry_id for entry_id, h in part if h not in known]
        if missing:
            with source_factory() as session:
                # an entry deleted from the source since the plan is left out
                data = entries_repo.existing_entry_data(session, missing)
                images = _source_images(session, missing)
            with session_scope(dest_factory) as session:
                added = _write_batch(session, dest, plan, data, images)
            copied += added
            already += len(data) - added
        already += len(part) - len(missing)
        if progress is not None:
            progress(start + len(part), len(plan.rows))
    return copied, already


def split_map(
    table: TileTable,
    group: str,
    source_url: str,
    dest_url: str,
    *,
    batch_rows: int = DEFAULT_BATCH_ROWS,
    progress: Callable[[int, int], None] | None = None,
) -> SplitSummary:
    """Copy the entries of ``group``'s tiles of the table's map from ``source_url`` into
    ``dest_url`` (migrated first; the map created there if absent). Refuses
    (InvalidInputError, NotFoundError, ConflictError) before writing anything: an
    unknown group, the same database twice, a source without the map or not at the
    newest schema, a destination map of that name that is another map."""
    from monoloc.server.storage.migrate import current_revision, head_revision, upgrade_database

    if batch_rows < 1:
        raise InvalidInputError(f"batch rows must be >= 1, got {batch_rows}")
    if group not in table.groups:
        raise InvalidInputError(
            f"group {group!r} is not in the tile table (groups: {', '.join(sorted(table.groups))})"
        )
    if same_database(source_url, dest_url):
        raise InvalidInputError(
            f"source and destination are the same database ({redact_url(dest_url)})"
        )
    revision, head = current_revision(source_url), head_revision()
    if revision != head:
        raise InvalidInputError(
            f"the source database {redact_url(source_url)} is at revision "
            f"{revision or 'none'}, not {head}: `monoloc db upgrade --database-url` it first"
        )
    started = time.perf_counter()
    source_engine = create_engine_for_url(source_url)
    dest_engine = None
    try:
        source_factory = make_session_factory(source_engine)
        with source_factory() as session:
            plan = plan_split(session, table, group)
        upgrade_database(dest_url)
        dest_engine = create_engine_for_url(dest_url)
        dest_factory = make_session_factory(dest_engine)
        with source_factory() as source_session, session_scope(dest_factory) as dest_session:
            dest = _prepare_destination(source_session, dest_session, plan)
        copied, already = copy_entries(
            source_factory, dest_factory, plan, dest, batch_rows, progress
        )
        with dest_factory() as session:
            final = maps_repo.get_map(session, dest.record.id)
    finally:
        source_engine.dispose()
        if dest_engine is not None:
            dest_engine.dispose()
    return SplitSummary(
        map_name=final.name,
        map_id=final.id,
        created=dest.created,
        in_group=len(plan.rows),
        copied=copied,
        already_there=already,
        outside=plan.n_entries - len(plan.rows),
        runs_copied=dest.runs_copied,
        vocabularies_copied=dest.vocabularies_copied,
        calibration=dest.calibration,
        seconds=time.perf_counter() - started,
        version=final.version,
    )

"""Bulk tiling: a large map made of perturbed geographic copies of real maps
(``monoloc map bulk-tile``), to size a deployment (disk, replica memory, start-up,
latency) before a real city of that size is mapped.

The sources are maps ingested the ordinary way (``monoloc map ingest``). Tile ``k`` is a
copy of source ``k % S`` centred on cell ``k`` of a grid of ``columns`` columns filled row
by row (pitch: the largest source's diagonal plus a margin), turned about the source's
centre by a random angle; a tile's place and turn depend only on ``k`` and the seed, so
a map grown in steps or resumed after an interruption is the map written at once.
The first ``S`` tiles are the sources unchanged and unturned (a frame of a source
localizes there, at its pose moved by the tile); every later tile perturbs its
entries so that no two copies are equal: each descriptor bit flips with probability
``2**-flip_halvings`` and a share of each entry's descriptors is replaced by descriptors
of another entry of the same source; VLAD and code are recomputed from the perturbed
descriptors with the destination map's vocabulary. 3D points are stored in the camera
frame, so they move with the tile's camera pose.

Rows are written in large transactions (``batch_rows`` per commit) and keep the map's
invariants as ``entries.add_entry`` does: every row passes ``check_new_entry``, the map
version rises by one per entry with one ``add`` row in the change log each (replicas
apply it as deltas or rebuild), the vocabulary id is the map's. Entry hashes are derived
from (tile, source hash), so a rerun after an interruption adds only what is missing.
"""

from __future__ import annotations

import hashlib
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from sqlalchemy import func, insert, select, update
from sqlalchemy.orm import Session, sessionmaker

from monoloc.core.errors import InvalidInputError
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.entry_checks import check_new_entry
from monoloc.server.storage.models import Entry, Map, MapChange, utc_now
from monoloc.server.storage.records import EntryData, MapRecord, NewEntry


@dataclass(frozen=True)
class TileConfig:
    """How to tile: ``entries`` the destination map's size when done (the last tile may
    be partial); ``columns`` of the tile grid; ``margin_m`` between tiles; each
    descriptor bit flips with probability ``2**-flip_halvings``; ``swap_share`` of an
    entry's descriptors come from another entry; ``batch_rows`` rows per transaction;
    ``seed`` fixes turns and perturbations."""

    entries: int
    columns: int = 32
    margin_m: float = 100.0
    flip_halvings: int = 4
    swap_share: float = 0.2
    batch_rows: int = 10_000
    seed: int = 0

    def validate(self) -> None:
        if self.entries < 1:
            raise InvalidInputError(f"entries must be >= 1, got {self.entries}")
        if self.columns < 1:
            raise InvalidInputError(f"columns must be >= 1, got {self.columns}")
        if not (math.isfinite(self.margin_m) and self.margin_m >= 0):
            raise InvalidInputError(f"margin_m must be >= 0, got {self.margin_m}")
        if not 1 <= self.flip_halvings <= 16:
            raise InvalidInputError(f"flip_halvings must be 1..16, got {self.flip_halvings}")
        if not 0.0 <= self.swap_share < 1.0:
            raise InvalidInputError(f"swap_share must be in [0, 1), got {self.swap_share}")
        if self.batch_rows < 1:
            raise InvalidInputError(f"batch_rows must be >= 1, got {self.batch_rows}")


@dataclass(frozen=True)
class Tile:
    """One copy: of source ``source``, moved by ``T_world_from_source`` (4, 4) float64
    (a turn about z and a shift), perturbed unless it is a source's first copy."""

    index: int
    source: int
    T_world_from_source: np.ndarray
    perturbed: bool


@dataclass(frozen=True)
class BulkSummary:
    map_id: int
    entries_added: int
    entries_total: int
    tiles: int
    seconds: float
    version: int

    @property
    def entries_per_s(self) -> float:
        return self.entries_added / self.seconds if self.seconds > 0 else float("nan")


@dataclass(frozen=True)
class _Source:
    record: MapRecord
    entries: list[EntryData]
    centre_m: np.ndarray  # (2,) middle of the entries' bounding box
    diagonal_m: float


def tile_layout(n_tiles: int, sources: list[_Source], config: TileConfig) -> list[Tile]:
    """The first ``n_tiles`` tiles (each tile's turn drawn from its own seed)."""
    pitch_m = max(s.diagonal_m for s in sources) + config.margin_m
    columns = config.columns
    tiles = []
    for k in range(n_tiles):
        source = k % len(sources)
        turn = np.random.default_rng([config.seed, 0, k]).uniform(-math.pi, math.pi)
        theta = 0.0 if k < len(sources) else float(turn)
        c, s = math.cos(theta), math.sin(theta)
        cell = np.array([k % columns, k // columns], dtype=np.float64) * pitch_m
        centre = sources[source].centre_m
        T = np.eye(4)
        T[:2, :2] = [[c, -s], [s, c]]
        T[:2, 3] = cell - T[:2, :2] @ centre  # turned about the source's centre, put at the cell's
        tiles.append(Tile(k, source, T, perturbed=k >= len(sources)))
    return tiles


def tile_hash(tile_index: int, source_hash: str) -> str:
    """The entry hash of a source entry's copy in a tile (sha256 hex)."""
    return hashlib.sha256(f"monoloc-tile:{tile_index}:{source_hash}".encode()).hexdigest()


def perturb_descriptors(
    descriptors: np.ndarray,
    donors: np.ndarray,
    flip_halvings: int,
    swap_share: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """(N, 32) uint8 -> (N, 32) uint8: ``round(swap_share * N)`` rows replaced by rows of
    ``donors`` (M, 32), then every bit flipped with probability ``2**-flip_halvings``
    (a mask that is the AND of ``flip_halvings`` random bytes)."""
    out = np.array(descriptors, dtype=np.uint8, copy=True)
    n_swap = int(round(swap_share * len(out)))
    if n_swap and len(donors):
        rows = rng.choice(len(out), n_swap, replace=False)
        out[rows] = donors[rng.integers(0, len(donors), n_swap)]
    mask = rng.integers(0, 256, out.shape, dtype=np.uint8)
    for _ in range(flip_halvings - 1):
        mask &= rng.integers(0, 256, out.shape, dtype=np.uint8)
    return out ^ mask


def _load_source(session: Session, ref: str | int) -> _Source:
    record = maps_repo.find_map(session, ref)
    ids = session.scalars(select(Entry.id).where(Entry.map_id == record.id).order_by(Entry.id))
    data = entries_repo.get_entry_data(session, list(ids))
    if not data:
        raise InvalidInputError(f"source map {record.name!r} has no entries")
    xy = np.array([[e.summary.x_m, e.summary.y_m] for e in data])
    low, high = xy.min(axis=0), xy.max(axis=0)
    return _Source(record, data, (low + high) / 2.0, float(np.hypot(*(high - low))))


def _check_compatible(dest: MapRecord, sources: list[MapRecord]) -> None:
    for source in sources:
        if source.id == dest.id:
            raise InvalidInputError(f"map {dest.name!r} cannot be its own source")
        if source.camera != dest.camera:
            raise InvalidInputError(
                f"source map {source.name!r} has camera {source.camera}, "
                f"map {dest.name!r} has {dest.camera}"
            )
        if (source.features or {}) != (dest.features or {}):
            raise InvalidInputError(
                f"source map {source.name!r} picks its corners by "
                f"{source.features}, map {dest.name!r} by {dest.features}"
            )


def _tile_entries(
    tile: Tile, source: _Source, positions: list[int], config: TileConfig, vocabulary
) -> list[NewEntry]:
    """The tile's copies of the source entries at ``positions`` (each entry's
    perturbation drawn from its own seed: the same in any batch)."""
    from monoloc.server.vision.binary_code import vlad_binary_code
    from monoloc.server.vision.vlad import compute_vlad_batch

    picked = [source.entries[i] for i in positions]
    descriptors = [e.descriptors for e in picked]
    if tile.perturbed:
        n = len(source.entries)
        perturbed = []
        for i, d in zip(positions, descriptors, strict=True):
            rng = np.random.default_rng([config.seed, 1, tile.index, i])
            donor = source.entries[(i + 1 + int(rng.integers(0, n - 1))) % n if n > 1 else i]
            perturbed.append(
                perturb_descriptors(
                    d, donor.descriptors, config.flip_halvings, config.swap_share, rng
                )
            )
        descriptors = perturbed
        vlads = compute_vlad_batch(descriptors, vocabulary)
    else:
        vlads = np.stack([e.vlad for e in picked])
    return [
        NewEntry(
            source_image_hash=tile_hash(tile.index, e.summary.source_image_hash),
            T_world_from_cam=tile.T_world_from_source @ e.T_world_from_cam,
            vlad=vlads[j],
            code=vlad_binary_code(vlads[j]),
            keypoints_px=e.keypoints_px,
            descriptors=descriptors[j],
            points_cam=e.points_cam,
            image_width_px=e.summary.image_width_px,
            image_height_px=e.summary.image_height_px,
            tags=(),
            timestamp_s=e.summary.timestamp_s,
        )
        for j, e in enumerate(picked)
    ]


def write_entries(session: Session, map_id: int, entries: list[NewEntry]) -> list[int]:
    """Insert ``entries`` (checked by ``check_new_entry``, without tags or images) into
    the map in one statement, skipping hashes the map already holds; the map's version
    rises by one per new entry, each with its ``add`` row in the change log. Returns the
    new entries' ids. Does not commit."""
    # A write first: it takes the map's write lock (SQLite: the database's), so that no
    # other bulk writer adds one of these hashes between the look and the insert.
    session.execute(
        update(Map)
        .where(Map.id == map_id)
        .values(version=Map.version)
        .execution_options(synchronize_session=False)
    )
    hashes = [e.source_image_hash for e in entries]
    known = entries_repo.existing_hashes(session, map_id, hashes)
    fresh = [e for e in entries if e.source_image_hash not in known]
    if any(e.tags or e.image is not None for e in fresh):
        raise InvalidInputError("bulk entries carry no tags or images")
    if not fresh:
        return []
    version = session.execute(
        update(Map)
        .where(Map.id == map_id)
        .values(version=Map.version + len(fresh), updated_at=utc_now())
        .returning(Map.version, Map.vocabulary_id)
        .execution_options(synchronize_session=False)
    ).one()
    last_version, vocabulary_id = int(version[0]), int(version[1])
    now = utc_now()
    rows = []
    for entry in fresh:
        values = check_new_entry(entry, entry.source_image_hash)
        values.update(map_id=map_id, run_id=None, vocabulary_id=vocabulary_id, created_at=now)
        rows.append(values)
    ids = session.scalars(
        insert(Entry).returning(Entry.id, sort_by_parameter_order=True), rows
    ).all()
    first_version = last_version - len(fresh) + 1
    changes = [
        dict(
            map_id=map_id, version=first_version + i, kind="add", entry_id=int(i_d), created_at=now
        )
        for i, i_d in enumerate(ids)
    ]
    session.execute(insert(MapChange), changes)
    if session.get_bind().dialect.name == "postgresql":
        channel = maps_repo.CHANGES_CHANNEL
        session.execute(select(func.pg_notify(channel, f"{map_id}:{last_version}")))
    return [int(i) for i in ids]


@dataclass(frozen=True)
class TilingPlan:
    """What :func:`write_tiles` writes: the checked destination and sources, the tiles,
    and (tile index, source position) of every entry of the finished map."""

    dest: MapRecord
    sources: list[_Source]
    vocabulary: object  # monoloc.server.vision.vocabulary.Vocabulary
    tiles: list[Tile]
    rows: list[tuple[int, int]]
    config: TileConfig


def prepare_tiling(
    session_factory: sessionmaker[Session],
    map_ref: str | int,
    source_refs: list[str | int],
    config: TileConfig,
) -> TilingPlan:
    """Check the request (InvalidInputError / NotFoundError: bad values, a missing or
    empty source, another camera or corner rule, the destination as its own source) and
    load the sources' entries."""
    config.validate()
    if not source_refs:
        raise InvalidInputError("bulk tiling needs at least one source map")
    from monoloc.server.vision.vocabulary import Vocabulary

    with session_scope(session_factory) as session:
        dest = maps_repo.find_map(session, map_ref)
        _check_compatible(dest, [maps_repo.find_map(session, ref) for ref in source_refs])
        sources = [_load_source(session, ref) for ref in source_refs]
        vocab = maps_repo.get_vocabulary(session, dest.vocabulary_id)
    vocabulary = Vocabulary.from_centres(np.asarray(vocab.centres), vocab.description)
    rows = _plan(sources, config)
    tiles = tile_layout(rows[-1][0] + 1, sources, config)
    return TilingPlan(dest, sources, vocabulary, tiles, rows, config)


def write_tiles(
    session_factory: sessionmaker[Session],
    plan: TilingPlan,
    progress: Callable[[int, int], None] | None = None,
) -> BulkSummary:
    """Write the plan's entries, ``batch_rows`` per transaction (``progress(done,
    total)`` after each); entries already in the map are skipped."""
    config, started, added = plan.config, time.perf_counter(), 0
    sources = plan.sources
    for start in range(0, len(plan.rows), config.batch_rows):
        part = plan.rows[start : start + config.batch_rows]
        hashes = [
            tile_hash(t, sources[plan.tiles[t].source].entries[i].summary.source_image_hash)
            for t, i in part
        ]
        with session_scope(session_factory) as session:
            known = entries_repo.existing_hashes(session, plan.dest.id, hashes)
        batch: list[NewEntry] = []
        missing = [row for row, h in zip(part, hashes, strict=True) if h not in known]
        for tile_index, positions in _group(missing):
            tile = plan.tiles[tile_index]
            batch += _tile_entries(tile, sources[tile.source], positions, config, plan.vocabulary)
        if batch:
            with session_scope(session_factory) as session:
                added += len(write_entries(session, plan.dest.id, batch))
        if progress is not None:
            progress(start + len(part), len(plan.rows))
    seconds = time.perf_counter() - started
    with session_scope(session_factory) as session:
        final = maps_repo.get_map(session, plan.dest.id)
    return BulkSummary(
        plan.dest.id, added, final.n_entries, len(plan.tiles), seconds, final.version
    )


def bulk_tile(
    session_factory: sessionmaker[Session],
    map_ref: str | int,
    source_refs: list[str | int],
    config: TileConfig,
    progress: Callable[[int, int], None] | None = None,
) -> BulkSummary:
    """Fill map ``map_ref`` with tiles of the ``source_refs`` maps until it holds
    ``config.entries`` entries (see the module docstring)."""
    plan = prepare_tiling(session_factory, map_ref, source_refs, config)
    return write_tiles(session_factory, plan, progress)


def _plan(sources: list[_Source], config: TileConfig) -> list[tuple[int, int]]:
    """(tile index, source position) of every entry of the finished map, tile by tile."""
    plan: list[tuple[int, int]] = []
    tile = 0
    while len(plan) < config.entries:
        n = len(sources[tile % len(sources)].entries)
        plan += [(tile, i) for i in range(min(n, config.entries - len(plan)))]
        tile += 1
    return plan


def _group(part: list[tuple[int, int]]) -> list[tuple[int, list[int]]]:
    """The positions of each tile, tiles in order: [(tile, [position, ...]), ...]."""
    groups: list[tuple[int, list[int]]] = []
    for tile, position in part:
        if groups and groups[-1][0] == tile:
            groups[-1][1].append(position)
        else:
            groups.append((tile, [position]))
    return groups

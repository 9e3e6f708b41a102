"""Repository of vocabularies and maps (camera, vocabulary, version counter, calibration).

Every function takes an open Session and never commits: the caller owns the unit of
work (``db.session_scope``). Functions return frozen records, not ORM objects.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from sqlalchemy import Select, delete, func, insert, select, update
from sqlalchemy.orm import Session

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import ConflictError, InvalidInputError, NotFoundError
from monoloc.server.storage._sql import insert_or_ignore
from monoloc.server.storage.arrays import CENTRES, pack_array, unpack_array
from monoloc.server.storage.models import (
    CHANGE_KINDS,
    Entry,
    Map,
    MapChange,
    Vocabulary,
    utc_now,
)
from monoloc.server.storage.records import MapChangeRecord, MapRecord, VocabularyRecord
from monoloc.server.vision.sizes import N_WORDS

MAP_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
# Calibration of the measurement model (docs/method.md section 7): key -> shape.
CALIBRATION_SHAPES = {"mu1": (3,), "Sigma1": (3, 3), "mu2": (4,), "Sigma2": (4, 4)}


# --- vocabularies ---------------------------------------------------------------------


def _vocabulary_record(row: Vocabulary) -> VocabularyRecord:
    return VocabularyRecord(
        id=row.id,
        version_hash=row.version_hash,
        n_words=row.n_words,
        description=row.description,
        created_at=row.created_at,
        centres=unpack_array(row.centres, CENTRES, f"vocabularies.centres id={row.id}"),
    )


def get_or_create_vocabulary(
    session: Session, centres: np.ndarray, description: str = ""
) -> tuple[VocabularyRecord, bool]:
    """Store the (64, 32) float32 ``centres`` unless a vocabulary with the same hash exists.

    Returns (record, created). ``description`` says how it was trained. The hash is the
    vision core's ``vocabulary_hash`` (so it equals ``Vocabulary.version``).
    """
    from monoloc.server.vision.vocabulary import vocabulary_hash

    blob = pack_array(centres, CENTRES, "vocabulary centres")
    version_hash = vocabulary_hash(np.frombuffer(blob, dtype=np.float32).reshape(CENTRES[1]))
    values = {
        "version_hash": version_hash,
        "centres": blob,
        "n_words": N_WORDS,
        "description": description,
        "created_at": utc_now(),
    }
    new_id = insert_or_ignore(session, Vocabulary, values, ["version_hash"])
    return get_vocabulary_by_hash(session, version_hash), new_id is not None


def get_vocabulary(session: Session, vocabulary_id: int) -> VocabularyRecord:
    row = session.get(Vocabulary, vocabulary_id)
    if row is None:
        raise NotFoundError(f"vocabulary {vocabulary_id} does not exist")
    return _vocabulary_record(row)


def get_vocabulary_by_hash(session: Session, version_hash: str) -> VocabularyRecord:
    row = session.scalars(select(Vocabulary).where(Vocabulary.version_hash == version_hash)).first()
    if row is None:
        raise NotFoundError(f"vocabulary with hash {version_hash!r} does not exist")
    return _vocabulary_record(row)


# --- maps -----------------------------------------------------------------------------


def _map_query() -> Select:
    n_entries = select(func.count(Entry.id)).where(Entry.map_id == Map.id).scalar_subquery()
    # populate_existing: version/calibration change through UPDATE statements, so a Map
    # already in the session's identity map must be refreshed.
    return (
        select(Map, Vocabulary.version_hash, n_entries)
        .join(Vocabulary, Map.vocabulary_id == Vocabulary.id)
        .execution_options(populate_existing=True)
    )


def _map_record(row: Map, vocab_hash: str, n_entries: int) -> MapRecord:
    camera = CameraIntrinsics(
        fx=row.fx, fy=row.fy, cx=row.cx, cy=row.cy, width_px=row.width_px, height_px=row.height_px
    )
    return MapRecord(
        id=row.id,
        name=row.name,
        camera=camera,
        vocabulary_id=row.vocabulary_id,
        vocabulary_hash=vocab_hash,
        version=row.version,
        calibration=row.calibration,
        n_entries=int(n_entries),
        created_at=row.created_at,
        updated_at=row.updated_at,
        geo_reference=row.geo_reference,
        features=row.features,
    )


def create_map(
    session: Session,
    name: str,
    camera: CameraIntrinsics,
    vocabulary_id: int,
    features: Mapping[str, Any] | None = None,
) -> MapRecord:
    """Create an empty map; ConflictError if the name is taken (the session stays usable).
    ``features``: how its entries will pick their ORB corners; None: the way this server's
    entry builder does (``vision.features.selection_rule`` of the default ``OrbConfig``)."""
    if features is None:
        from monoloc.server.vision.features import selection_rule

        features = selection_rule()
    if not isinstance(name, str) or not MAP_NAME_RE.match(name):
        raise InvalidInputError(
            f"invalid map name {name!r}: 1-64 letters, digits, '.', '_' or '-', "
            "starting with a letter or digit"
        )
    get_vocabulary(session, vocabulary_id)
    now = utc_now()
    values = {
        "name": name,
        "fx": float(camera.fx),
        "fy": float(camera.fy),
        "cx": float(camera.cx),
        "cy": float(camera.cy),
        "width_px": int(camera.width_px),
        "height_px": int(camera.height_px),
        "vocabulary_id": vocabulary_id,
        "version": 0,
        "features": dict(features),
        "created_at": now,
        "updated_at": now,
    }
    map_id = insert_or_ignore(session, Map, values, ["name"])
    if map_id is None:
        raise ConflictError(f"a map named {name!r} already exists")
    return get_map(session, map_id)


def get_map(session: Session, map_id: int) -> MapRecord:
    found = session.execute(_map_query().where(Map.id == map_id)).first()
    if found is None:
        raise NotFoundError(f"map {map_id} does not exist")
    return _map_record(*found)


def get_map_by_name(session: Session, name: str) -> MapRecord:
    found = session.execute(_map_query().where(Map.name == name)).first()
    if found is None:
        raise NotFoundError(f"map {name!r} does not exist")
    return _map_record(*found)


def find_map(session: Session, ref: int | str) -> MapRecord:
    """A map by id (an int or a string of digits) or else by name."""
    if isinstance(ref, int) or (isinstance(ref, str) and ref.isdigit()):
        return get_map(session, int(ref))
    return get_map_by_name(session, ref)


def list_maps(session: Session) -> list[MapRecord]:
    return [_map_record(*row) for row in session.execute(_map_query().order_by(Map.id))]


def delete_map(session: Session, map_id: int) -> None:
    """Delete a map; the database cascades to its runs, entries and tags."""
    result = session.execute(
        delete(Map).where(Map.id == map_id).execution_options(synchronize_session=False)
    )
    if result.rowcount == 0:
        raise NotFoundError(f"map {map_id} does not exist")
    session.expire_all()


CHANGES_CHANNEL = "monoloc_map_changes"  # PostgreSQL NOTIFY channel: "<map id>:<version>"


def bump_map_version(session: Session, map_id: int, kind: str, entry_id: int | None = None) -> int:
    """Increment the map's version counter (takes the write lock) and append the change
    that made it (``kind`` of ``models.CHANGE_KINDS``, about ``entry_id``) to the map's
    log in the same transaction; returns the new version. On PostgreSQL the commit also
    notifies ``CHANGES_CHANNEL`` so that replicas apply it at once."""
    if kind not in CHANGE_KINDS:
        raise InvalidInputError(f"change kind must be one of {CHANGE_KINDS}, got {kind!r}")
    now = utc_now()
    result = session.execute(
        update(Map)
        .where(Map.id == map_id)
        .values(version=Map.version + 1, updated_at=now)
        .returning(Map.version)
        .execution_options(synchronize_session=False)
    )
    version = result.scalar_one_or_none()
    if version is None:
        raise NotFoundError(f"map {map_id} does not exist")
    session.execute(
        insert(MapChange).values(
            map_id=map_id, version=int(version), kind=kind, entry_id=entry_id, created_at=now
        )
    )
    if session.get_bind().dialect.name == "postgresql":
        session.execute(select(func.pg_notify(CHANGES_CHANNEL, f"{map_id}:{int(version)}")))
    return int(version)


def list_changes(
    session: Session, map_id: int, after_version: int, limit: int = 10_000
) -> list[MapChangeRecord]:
    """The map's changes with a version above ``after_version``, in version order."""
    stmt = (
        select(MapChange)
        .where(MapChange.map_id == map_id, MapChange.version > after_version)
        .order_by(MapChange.version)
        .limit(limit)
    )
    return [MapChangeRecord(r.map_id, r.version, r.kind, r.entry_id) for r in session.scalars(stmt)]


def map_versions(session: Session) -> dict[int, int]:
    """Every map's id -> current version (one cheap query; replicas poll it)."""
    return {int(i): int(v) for i, v in session.execute(select(Map.id, Map.version))}


def set_map_vocabulary(session: Session, map_id: int, vocabulary_id: int) -> MapRecord:
    """Point the map at another vocabulary and bump its version. Entries keep their old
    VLADs (and vocabulary_id) until a job recomputes them (entries.update_entry_vlad)."""
    get_vocabulary(session, vocabulary_id)
    session.execute(
        update(Map)
        .where(Map.id == map_id)
        .values(vocabulary_id=vocabulary_id)
        .execution_options(synchronize_session=False)
    )
    bump_map_version(session, map_id, "vocabulary")
    return get_map(session, map_id)


def validate_calibration(calibration: Mapping[str, Any]) -> dict[str, Any]:
    """Check mu1 (3,), Sigma1 (3, 3), mu2 (4,), Sigma2 (4, 4) (finite, covariances
    symmetric positive definite) and return a JSON-ready copy. Other keys (provenance,
    source, ...) are kept as given and must be JSON-serialisable."""
    import json

    if not isinstance(calibration, Mapping):
        raise InvalidInputError(f"calibration must be an object, got {type(calibration).__name__}")
    out: dict[str, Any] = {}
    for key, shape in CALIBRATION_SHAPES.items():
        if key not in calibration:
            raise InvalidInputError(f"calibration is missing {key!r}")
        try:
            value = np.asarray(calibration[key], dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"calibration {key} is not numeric: {exc}") from exc
        if value.shape != shape or not np.all(np.isfinite(value)):
            raise InvalidInputError(
                f"calibration {key} must be finite with shape {shape}, got {value.shape}"
            )
        if len(shape) == 2:
            if not np.allclose(value, value.T, atol=1e-9 * max(1.0, float(np.abs(value).max()))):
                raise InvalidInputError(f"calibration {key} is not symmetric")
            if np.linalg.eigvalsh(value).min() <= 0.0:
                raise InvalidInputError(f"calibration {key} is not positive definite")
        out[key] = value.tolist()
    for key, value in calibration.items():
        if key not in out:
            try:
                out[key] = json.loads(json.dumps(value, allow_nan=False))
            except (TypeError, ValueError) as exc:
                raise InvalidInputError(f"calibration {key!r} is not JSON: {exc}") from exc
    return out


def set_calibration(
    session: Session, map_id: int, calibration: Mapping[str, Any] | None
) -> MapRecord:
    """Store (or clear, with None) the map's measurement-model calibration."""
    value = None if calibration is None else validate_calibration(calibration)
    row = session.get(Map, map_id)
    if row is None:
        raise NotFoundError(f"map {map_id} does not exist")
    row.calibration = value
    session.flush()
    return get_map(session, map_id)


def update_calibration(
    session: Session,
    map_id: int,
    change: Callable[[dict[str, Any] | None], Mapping[str, Any] | None],
) -> MapRecord:
    """Store ``change(stored calibration)`` (read, changed and written under the map's
    write lock), so that two writers (a base and a condition calibration finishing
    together) do not lose each other's part. NotFoundError if the map does not exist."""
    # A write first: on SQLite it takes the database's write lock before the read (a
    # plain read would see a snapshot another writer may change meanwhile); on
    # PostgreSQL it locks the row.
    locked = session.execute(
        update(Map)
        .where(Map.id == map_id)
        .values(calibration=Map.calibration)
        .execution_options(synchronize_session=False)
    )
    if locked.rowcount == 0:
        raise NotFoundError(f"map {map_id} does not exist")
    return set_calibration(session, map_id, change(get_map(session, map_id).calibration))


def set_geo_reference(
    session: Session, map_id: int, geo_reference: Mapping[str, Any] | None
) -> MapRecord:
    """Store (or clear, with None) the map's geographic reference: a dict checked by
    ``monoloc.core.geo.GeoReference.from_dict`` (InvalidInputError if it is none)."""
    from monoloc.core.geo import GeoReference

    value = None if geo_reference is None else GeoReference.from_dict(geo_reference).to_dict()
    row = session.get(Map, map_id)
    if row is None:
        raise NotFoundError(f"map {map_id} does not exist")
    row.geo_reference = value
    session.flush()
    return get_map(session, map_id)

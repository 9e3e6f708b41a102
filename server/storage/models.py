"""SQLAlchemy 2.x models of the map database (the schema Alembic's 0001 revision creates).

Array columns are raw blobs whose dtype and shape are fixed by ``monoloc.server.storage.arrays``
(VLAD (2048,) float32, code (256,) uint8, keypoints (N, 2) float32 pixels, descriptors
(N, 32) uint8, points (N, 3) float32 in the reference camera frame (OpenCV), pose 4x4
float64 ``T_world_from_cam`` row-major). Timestamps are timezone-aware UTC.

Deleting a map cascades in the database (``ON DELETE CASCADE``) to its runs, entries
and entry tags; jobs keep their history with ``map_id`` set to NULL.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    JSON,
    CheckConstraint,
    DateTime,
    ForeignKey,
    Index,
    LargeBinary,
    MetaData,
    String,
    Text,
    TypeDecorator,
    UniqueConstraint,
    text,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship

RUN_STATUSES = ("pending", "running", "done", "failed", "interrupted")
JOB_STATES = ("queued", "running", "done", "failed", "interrupted")
SOURCE_FORMATS = ("kitti", "tum", "single", "colmap", "kapture", "rosbag")

NAMING_CONVENTION = {
    "ix": "ix_%(table_name)s_%(column_0_N_name)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


def utc_now() -> datetime:
    """The current time, timezone-aware UTC."""
    return datetime.now(UTC)


class UtcDateTime(TypeDecorator[datetime]):
    """A DATETIME that always comes back timezone-aware UTC (SQLite stores it naive)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            value = value.replace(tzinfo=UTC)
        return value.astimezone(UTC)

    def process_result_value(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            return value.replace(tzinfo=UTC)
        return value.astimezone(UTC)


def _in(column: str, values: tuple[str, ...]) -> str:
    return f"{column} IN ({', '.join(repr(v) for v in values)})"


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING_CONVENTION)
    type_annotation_map = {datetime: UtcDateTime(), dict[str, Any]: JSON()}


class Vocabulary(Base):
    __tablename__ = "vocabularies"

    id: Mapped[int] = mapped_column(primary_key=True)
    version_hash: Mapped[str] = mapped_column(String(64), unique=True)
    centres: Mapped[bytes] = mapped_column(LargeBinary)  # (64, 32) float32
    n_words: Mapped[int]
    description: Mapped[str] = mapped_column(Text, default="")
    created_at: Mapped[datetime] = mapped_column(default=utc_now)


class Map(Base):
    __tablename__ = "maps"
    __table_args__ = (
        CheckConstraint("fx > 0 AND fy > 0", name="focal_positive"),
        CheckConstraint("width_px > 0 AND height_px > 0", name="size_positive"),
        CheckConstraint("version >= 0", name="version_nonnegative"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    fx: Mapped[float]
    fy: Mapped[float]
    cx: Mapped[float]
    cy: Mapped[float]
    width_px: Mapped[int]
    height_px: Mapped[int]
    vocabulary_id: Mapped[int] = mapped_column(ForeignKey("vocabularies.id"), index=True)
    # Bumped on every entry add/remove/re-describe and vocabulary change; indexes are
    # stamped with it so a stale index is detected.
    version: Mapped[int] = mapped_column(default=0, server_default=text("0"))
    calibration: Mapped[dict[str, Any] | None]
    # WGS84 reference of the map's world (monoloc/core/geo.py GeoReference.to_dict), or NULL.
    geo_reference: Mapped[dict[str, Any] | None]
    # How the map's entries picked their ORB corners (vision.features.selection_rule), set
    # when the map is created; maps from before revision 0007 say {"rule": "strongest"}.
    features: Mapped[dict[str, Any] | None]
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
    updated_at: Mapped[datetime] = mapped_column(default=utc_now, onupdate=utc_now)


class Run(Base):
    __tablename__ = "runs"
    __table_args__ = (
        CheckConstraint(_in("status", RUN_STATUSES), name="status"),
        CheckConstraint(_in("source_format", SOURCE_FORMATS), name="source_format"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    map_id: Mapped[int] = mapped_column(ForeignKey("maps.id", ondelete="CASCADE"), index=True)
    kind: Mapped[str] = mapped_column(String(32))
    source_format: Mapped[str] = mapped_column(String(16))
    source_name: Mapped[str] = mapped_column(String(512), default="")
    status: Mapped[str] = mapped_column(String(16), default="pending")
    frames_total: Mapped[int] = mapped_column(default=0, server_default=text("0"))
    frames_done: Mapped[int] = mapped_column(default=0, server_default=text("0"))
    entries_added: Mapped[int] = mapped_column(default=0, server_default=text("0"))
    frames_skipped: Mapped[int] = mapped_column(default=0, server_default=text("0"))
    skip_reasons: Mapped[dict[str, Any]] = mapped_column(default=dict)  # reason -> count
    error: Mapped[str | None] = mapped_column(Text)
    # RunCorrection.summary() when the run was registered to the map (migration 0006)
    registration: Mapped[dict[str, Any] | None] = mapped_column()
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
    updated_at: Mapped[datetime] = mapped_column(default=utc_now, onupdate=utc_now)


class Entry(Base):
    __tablename__ = "entries"
    __table_args__ = (
        UniqueConstraint("map_id", "source_image_hash"),
        Index("ix_entries_map_id_x_m_y_m", "map_id", "x_m", "y_m"),
        CheckConstraint("n_points >= 0", name="n_points_nonnegative"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    map_id: Mapped[int] = mapped_column(ForeignKey("maps.id", ondelete="CASCADE"))
    run_id: Mapped[int | None] = mapped_column(
        ForeignKey("runs.id", ondelete="SET NULL"), index=True
    )
    source_image_hash: Mapped[str] = mapped_column(String(64))  # sha256 hex of the image file
    T_world_from_cam: Mapped[bytes] = mapped_column(LargeBinary)  # (4, 4) float64
    x_m: Mapped[float]
    y_m: Mapped[float]
    yaw_rad: Mapped[float]
    vocabulary_id: Mapped[int] = mapped_column(ForeignKey("vocabularies.id"), index=True)
    # The big blobs are deferred: listing entries does not load them.
    vlad: Mapped[bytes] = mapped_column(LargeBinary, deferred=True)  # (2048,) float32
    code: Mapped[bytes] = mapped_column(LargeBinary, deferred=True)  # (256,) uint8
    keypoints_px: Mapped[bytes] = mapped_column(LargeBinary, deferred=True)  # (N, 2) float32
    descriptors: Mapped[bytes] = mapped_column(LargeBinary, deferred=True)  # (N, 32) uint8
    points_cam: Mapped[bytes] = mapped_column(LargeBinary, deferred=True)  # (N, 3) float32
    n_points: Mapped[int]
    image_width_px: Mapped[int]
    image_height_px: Mapped[int]
    timestamp_s: Mapped[float | None]
    created_at: Mapped[datetime] = mapped_column(default=utc_now)

    tags: Mapped[list[EntryTag]] = relationship(
        cascade="all, delete-orphan", passive_deletes=True, order_by="EntryTag.tag"
    )


class EntryImage(Base):
    """A small grey JPEG of an entry's reference image (the console shows it), and the
    keypoints (N, 2) float32 in full-size pixels that got no 3D point (the entry keeps
    only the others). Optional: entries added before revision 0003 have none."""

    __tablename__ = "entry_images"
    __table_args__ = (CheckConstraint("width_px > 0 AND height_px > 0", name="size_positive"),)

    entry_id: Mapped[int] = mapped_column(
        ForeignKey("entries.id", ondelete="CASCADE"), primary_key=True
    )
    jpeg: Mapped[bytes] = mapped_column(LargeBinary)
    width_px: Mapped[int]  # of the JPEG, not of the full-size image
    height_px: Mapped[int]
    keypoints_without_point_px: Mapped[bytes] = mapped_column(LargeBinary)


class EntryTag(Base):
    __tablename__ = "entry_tags"

    entry_id: Mapped[int] = mapped_column(
        ForeignKey("entries.id", ondelete="CASCADE"), primary_key=True
    )
    tag: Mapped[str] = mapped_column(String(64), primary_key=True, index=True)


CHANGE_KINDS = ("add", "delete", "retag", "vlad", "vocabulary")


class MapChange(Base):
    """One step of a map's ordered change log: the edit that took the map to ``version``.

    Written in the transaction that bumps the version (``maps.bump_map_version``), so the
    log has no gap: replicas apply ``version > their own`` in order as deltas to their
    in-memory index (``runtime.MapRegistry.catch_up``). ``entry_id`` is not a foreign key:
    a deleted entry's row stays in the log."""

    __tablename__ = "map_changes"
    __table_args__ = (
        UniqueConstraint("map_id", "version"),
        CheckConstraint(_in("kind", CHANGE_KINDS), name="kind"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    map_id: Mapped[int] = mapped_column(ForeignKey("maps.id", ondelete="CASCADE"))
    version: Mapped[int]
    kind: Mapped[str] = mapped_column(String(16))
    entry_id: Mapped[int | None]
    created_at: Mapped[datetime] = mapped_column(default=utc_now)


class Job(Base):
    __tablename__ = "jobs"
    __table_args__ = (
        CheckConstraint(_in("state", JOB_STATES), name="state"),
        CheckConstraint("progress >= 0 AND progress <= 1", name="progress_range"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    kind: Mapped[str] = mapped_column(String(32))
    map_id: Mapped[int | None] = mapped_column(
        ForeignKey("maps.id", ondelete="SET NULL"), index=True
    )
    run_id: Mapped[int | None] = mapped_column(
        ForeignKey("runs.id", ondelete="SET NULL"), index=True
    )
    state: Mapped[str] = mapped_column(String(16), default="queued", index=True)
    progress: Mapped[float] = mapped_column(default=0.0, server_default=text("0"))
    message: Mapped[str] = mapped_column(Text, default="")
    error: Mapped[str | None] = mapped_column(Text)
    params: Mapped[dict[str, Any]] = mapped_column(default=dict)
    result: Mapped[dict[str, Any] | None]
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
    updated_at: Mapped[datetime] = mapped_column(default=utc_now, onupdate=utc_now)
    finished_at: Mapped[datetime | None]
    # The lease of the process running it (server/jobs/lease.py): who holds it, until when.
    lease_owner: Mapped[str | None] = mapped_column(String(128))
    lease_expires_at: Mapped[datetime | None] = mapped_column(index=True)
    attempts: Mapped[int] = mapped_column(default=0, server_default=text("0"))


class ApiKey(Base):
    """An API key. Only ``key_hash`` (sha256 hex of the whole key) is stored: keys are
    high-entropy random tokens, so a fast hash is enough (no password stretching needed)."""

    __tablename__ = "api_keys"

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(128))
    prefix: Mapped[str] = mapped_column(String(16), index=True)  # shown to humans
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)
    scopes: Mapped[str] = mapped_column(String(256))  # comma-separated
    # The map ids this key may touch (JSON list); NULL: every map (revision 0008)
    maps: Mapped[list[int] | None] = mapped_column(JSON, nullable=True)
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
    revoked_at: Mapped[datetime | None]


class Camera(Base):
    """A vehicle's camera, registered once (``POST /v1/cameras``) and named by its id in
    every query after (revision 0009): pinhole intrinsics in pixels for images of
    ``width_px`` x ``height_px``, and the lens distortion (ROS CameraInfo's model name
    and D), NULL for a pinhole. Never changed after it is registered (delete and
    register again); ``key_id`` is the key that registered it."""

    __tablename__ = "cameras"
    __table_args__ = (
        CheckConstraint("fx > 0 AND fy > 0", name="focal_positive"),
        CheckConstraint("width_px > 0 AND height_px > 0", name="size_positive"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(128))
    fx: Mapped[float]
    fy: Mapped[float]
    cx: Mapped[float]
    cy: Mapped[float]
    width_px: Mapped[int]
    height_px: Mapped[int]
    distortion_model: Mapped[str | None] = mapped_column(String(32))
    distortion: Mapped[list[float] | None] = mapped_column(JSON, nullable=True)
    key_id: Mapped[int | None] = mapped_column(
        ForeignKey("api_keys.id", ondelete="SET NULL"), index=True
    )
    created_at: Mapped[datetime] = mapped_column(default=utc_now)

"""Deployment settings of the map server, read from ``MONOLOC_*`` environment variables.

Nothing is read at import time: call :func:`get_settings` (or build ``Settings(...)``
directly in tests) where the settings are needed.

Durability (``sqlite_synchronous``)
-----------------------------------
The SQLite database runs in WAL mode. With ``NORMAL`` (the default) a commit is
durable against a crash of the application or the server process: the WAL is written
before the commit returns and SQLite replays it on the next open. A power loss or an
operating-system crash may lose the last few committed transactions (those not yet
checkpointed/fsynced), but never corrupts the database. ``FULL`` fsyncs the WAL on
every commit, so acknowledged commits also survive a power loss, at the price of one
fsync per transaction (ingestion commits in batches, so the cost is moderate).
``EXTRA`` additionally fsyncs the directory after a WAL reset.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

MiB = 1024 * 1024
GiB = 1024 * MiB


class Settings(BaseSettings):
    """All deployment knobs of the server (paths, database, limits, threads)."""

    model_config = SettingsConfigDict(env_prefix="MONOLOC_", extra="ignore", frozen=True)

    # --- storage -------------------------------------------------------------------
    data_dir: Path = Field(
        default=Path("data"), description="Directory holding the database and the indexes."
    )
    database_url: str = Field(
        default="",
        description="SQLAlchemy URL; empty means sqlite:///<data_dir>/monoloc.db (absolute).",
    )
    index_dir: Path | None = Field(
        default=None, description="Where retrieval indexes are persisted; default data_dir/index."
    )
    uploads_dir: Path | None = Field(
        default=None,
        description="Where uploaded runs wait for their ingestion job; default "
        "data_dir/uploads. Replicas on several machines must share it (a network mount): "
        "the replica that takes a job over reads the upload from here.",
    )
    sqlite_synchronous: Literal["NORMAL", "FULL", "EXTRA"] = Field(
        default="NORMAL",
        description="PRAGMA synchronous in WAL mode: NORMAL survives app crashes, FULL "
        "also power loss (see module docstring).",
    )
    busy_timeout_ms: int = Field(
        default=5000, ge=0, description="How long a writer waits for the SQLite write lock."
    )

    # --- HTTP server ---------------------------------------------------------------
    host: str = "127.0.0.1"
    port: int = Field(default=8000, ge=1, le=65535)
    max_body_bytes: int = Field(
        default=512 * MiB,
        gt=0,
        description="Largest request body of any route: recorded runs (archives, file sets).",
    )
    max_query_body_bytes: int = Field(
        default=8 * MiB, gt=0, description="Largest localize request (one query frame)."
    )
    max_entry_body_bytes: int = Field(
        default=64 * MiB,
        gt=0,
        description="Largest add-entry request (image + depth image or LiDAR scan).",
    )
    max_json_body_bytes: int = Field(
        default=1 * MiB, gt=0, description="Largest JSON body (keys, maps, tags, calibration)."
    )
    max_image_pixels: int = Field(
        default=25_000_000, gt=0, description="Largest decoded image (width * height)."
    )
    max_archive_members: int = Field(
        default=100_000, gt=0, description="Most files an uploaded tar/zip may contain."
    )
    max_archive_bytes: int = Field(
        default=4 * GiB,
        gt=0,
        description="Largest total uncompressed size of an archive: declared (a zip's "
        "central directory, before extracting; a tar's headers as they stream) and "
        "written (413).",
    )
    max_archive_ratio: float = Field(
        default=100.0,
        ge=1.0,
        description="Most an archive, and each zip member, may unpack to per compressed "
        "byte (413; images and LiDAR scans compress 1-3x, a zip bomb 1000x).",
    )
    archive_ratio_allowance_bytes: int = Field(
        default=1 * MiB,
        ge=0,
        description="Members up to this size, and this much of an archive's total, are "
        "exempt from max_archive_ratio (small text files compress far better).",
    )
    upload_disk_quota_bytes: int = Field(
        default=5 * GiB,
        gt=0,
        description="Disk one upload may occupy while it is unpacked: the received archive "
        "plus its files, each in whole 4 KiB blocks (413).",
    )
    uploads_disk_quota_bytes: int = Field(
        default=10 * GiB,
        gt=0,
        description="Disk all the uploads one server process unpacks at the same time may "
        "occupy together; one more is answered 507 with Retry-After (stored uploads "
        "waiting for their job are not counted).",
    )
    stream_max_pending_frames: int = Field(
        # 1: a vehicle's newest frame replaces the one still waiting (the freshest frame is
        # the one worth localizing). bench/load.py, 2 replicas at twice capacity over the
        # WebSocket: p99 1.1-1.2x the capacity p50 with 1, 2.0-3.1x with 2.
        default=1,
        ge=1,
        description="WebSocket frames queued per vehicle before stale drops.",
    )

    max_stream_backlog: int = Field(
        default=1000,
        ge=1,
        description="Answers (mostly 'dropped' notices) owed to one WebSocket client before "
        "the server closes the stream as flooding.",
    )
    max_lidar_points: int = Field(
        default=500_000, gt=0, description="Most points a LiDAR scan sent to the API may hold."
    )

    # --- API security (see server/api/deps.py) -------------------------------------
    bootstrap_admin_key: SecretStr | None = Field(
        default=None,
        description="If set and no API key exists yet, stored as an admin key at start-up "
        "(must look like a monoloc key: 'mlk_' + at least 32 URL-safe characters).",
    )
    metrics_public: bool = Field(
        default=False,
        description="Serve /metrics without an API key (only for a private scrape network); "
        "otherwise it needs an admin key.",
    )
    localize_seed: int | None = Field(
        default=None,
        description="Seed of the server's RNG seed sequence (RANSAC); None draws OS entropy. "
        "A request may pass its own seed.",
    )

    # --- threads (2-core machines: do not oversubscribe) ---------------------------
    worker_threads: int = Field(
        default=2, ge=1, description="Threads running CPU work off the event loop."
    )
    cv_threads: int = Field(default=1, ge=0, description="cv2.setNumThreads value.")
    faiss_threads: int = Field(default=1, ge=1, description="faiss.omp_set_num_threads value.")
    job_threads: int = Field(
        default=1, ge=1, description="Jobs (ingestion, vocabulary) running at the same time."
    )

    # --- admission control (server/api/admission.py) --------------------------------
    localize_queue_depth: int = Field(
        default=2,
        ge=0,
        description="Localize requests allowed to wait for a CPU slot (worker_threads "
        "compute); more are answered 503 with Retry-After at once. Under overload the "
        "queue is always full and every served frame waits for it, so keep it near "
        "worker_threads: one frame ready per worker (bench/load.py's generator at twice "
        "capacity: p99 of served frames 108-109 ms with 2 vs 214-233 ms with 4, served "
        "rate within noise).",
    )
    localize_deadline_ms: int = Field(
        default=2000,
        ge=1,
        description="Default deadline of a localize request (X-Request-Deadline-Ms "
        "overrides): not computed once it passed.",
    )
    body_stall_timeout_s: float = Field(
        default=30.0,
        gt=0,
        description="An admitted request whose body stops arriving for this long (or is "
        "not complete at its deadline) is answered 408 and its connection closed, freeing "
        "its lane's place (nginx's client_body_timeout, the same idea, defaults to 60 s).",
    )
    shutdown_grace_s: float = Field(
        default=8.0,
        gt=0,
        description="On SIGTERM, how long requests in flight may finish before they are "
        "cancelled (below Docker's 10-s stop timeout; jobs are leases and resume).",
    )
    write_threads: int = Field(
        default=1, ge=1, description="Map writes (entry builds, edits) computed at a time."
    )
    write_queue_depth: int = Field(
        default=16, ge=0, description="Map writes allowed to wait; more are answered 503."
    )
    write_deadline_ms: int = Field(
        default=30_000, ge=1, description="Default deadline of a map write."
    )
    read_threads: int = Field(
        default=1, ge=1, description="Costly reads (a map's poses, coverage) computed at a time."
    )
    read_queue_depth: int = Field(
        default=32, ge=0, description="Reads allowed in flight beyond those; more are 503."
    )
    read_deadline_ms: int = Field(default=10_000, ge=1, description="Default deadline of a read.")
    job_queue_depth: int = Field(
        default=4,
        ge=0,
        description="Run uploads / job submissions in flight beyond one; more are 503.",
    )

    job_lease_s: float = Field(
        default=15.0,
        gt=0,
        description="Lease of a running job; renewed every third of it. A replica that "
        "stops renewing (killed) loses its jobs to another after this long.",
    )
    job_poll_s: float = Field(
        default=1.0, gt=0, description="How often a replica looks for claimable jobs."
    )

    # --- replicas (server/runtime.py, server/api/consistency.py) -----------------------
    replica_sync_s: float = Field(
        default=0.25,
        gt=0,
        description="How often a replica polls the maps' versions to apply the change log "
        "(PostgreSQL's NOTIFY wakes it at once).",
    )
    key_cache_s: float = Field(
        default=2.0,
        ge=0,
        description="How long a replica trusts an API key it has verified before asking the "
        "database again (a key revoked through another replica is refused at the latest this "
        "long after; the revoking replica refuses it at once). 0: every request asks.",
    )
    min_version_wait_ms: int = Field(
        default=1000,
        ge=0,
        description="How long localize waits for X-Min-Map-Version before 503 stale_replica.",
    )

    @model_validator(mode="after")
    def _fill_derived_paths(self) -> Settings:
        # Settings is frozen; derived defaults are filled once, at construction.
        if not self.database_url:
            db_path = (self.data_dir / "monoloc.db").resolve()
            object.__setattr__(self, "database_url", f"sqlite:///{db_path}")
        if self.index_dir is None:
            object.__setattr__(self, "index_dir", self.data_dir / "index")
        if self.uploads_dir is None:
            object.__setattr__(self, "uploads_dir", self.data_dir / "uploads")
        return self


def get_settings(**overrides: object) -> Settings:
    """Read the settings from the environment now (not cached), with explicit overrides."""
    return Settings(**overrides)

"""Ingestion of a recorded run (KITTI sequence or TUM run) into a map.

Stages, for a source opened (and its metadata validated) by a reader:

1. hash: the identity of each selected image, ``hash_chunk`` frames at a time (threads):
   the hash of its decoded pixels (``common.content_hash``; the same picture re-encoded
   or with bytes appended is the same frame), and the sha256 of its bytes, under which
   maps stored before content hashing know their entries. Both are looked up in the map
   before any other work: a frame this run already added (an interrupted run, resumed)
   counts as added; one the map holds from elsewhere is skipped (``already_in_map``). So
   a re-run adds nothing twice, a resumed run continues where it stopped, and the run's
   counters add up: entries added + frames skipped = frames done.
2. build: decode, blur + ORB, 3D points from the LiDAR scan or depth image, VLAD
   (``monoloc.server.entry_builder.build_entry``) in a thread pool (OpenCV and numpy release the
   GIL; OpenCV and BLAS are limited to one thread each so 2 cores are not oversubscribed).
3. write: on the calling thread, in order, in batches of ``batch_size`` frames, each
   batch one transaction (entries + run counters); after each commit the registry's
   live index receives the new entries. An interruption loses at most one batch.

Frames skipped, and why: ``already_in_map`` (in the map, not from this run),
``too_few_points`` (fewer than ``BuildConfig.min_points`` keypoints with a 3D point),
``duplicate_image`` (the same image twice in one run), plus the readers' own (TUM: ``no_depth``,
``no_ground_truth``). A frame whose image, scan or depth file cannot be read or decoded
fails the ingestion with an error naming the file (the entries of earlier frames are
committed first and stay), unless ``skip_bad_frames`` is set: then it is skipped as
``unreadable_image`` / ``unreadable_scan`` / ``unreadable_depth`` / ``bad_image`` (wrong
size) and reported.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.geometry import planar_from_T_world_from_cam
from monoloc.core.registration import RegistrationConfig
from monoloc.server.entry_builder import BuildConfig, TooFewPointsError, build_entry
from monoloc.server.index.retrieval import RetrievalIndex
from monoloc.server.ingest.common import bytes_hash, content_hash, decode_gray, read_bytes
from monoloc.server.ingest.register import RegistrationTarget, register_source
from monoloc.server.localize import LocalizeConfig, ReferenceEntry
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage import runs as runs_repo
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.records import NewEntry
from monoloc.server.vision.features import orb_for_rule
from monoloc.server.vision.vocabulary import Vocabulary

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class IngestConfig:
    """``workers`` threads build entries; ``batch_size`` frames per transaction;
    ``skip_bad_frames``: skip (and report) unreadable frames instead of failing;
    ``register``: register the run to the map's entries from other runs before building
    (``monoloc.core.registration``; None: keep the written poses)."""

    build: BuildConfig = field(default_factory=BuildConfig)
    workers: int = 2
    batch_size: int = 24
    skip_bad_frames: bool = False
    hash_chunk: int = 256  # frames hashed and looked up in the map at a time
    register: RegistrationConfig | None = None

    def __post_init__(self) -> None:
        if self.workers < 1 or self.batch_size < 1 or self.hash_chunk < 1:
            raise InvalidInputError(f"invalid IngestConfig {self}")


@dataclass(frozen=True)
class IngestSummary:
    """What one ingestion did. ``points_*``: keypoints with a 3D point per added entry."""

    run_id: int
    map_id: int
    frames_total: int
    frames_done: int
    entries_added: int
    frames_skipped: int
    skip_reasons: dict[str, int]
    points_mean: float
    points_min: int
    elapsed_s: float
    frames_per_s: float
    map_version: int
    interrupted: bool = False
    registration: dict | None = None  # RunCorrection.summary() when the run was registered


@dataclass(frozen=True)
class _Outcome:
    frame: object
    entry: NewEntry | None = None
    raw_hash: str = ""  # the image file's sha256 (how older maps know the image)
    skip_reason: str | None = None
    error: InvalidInputError | None = None


def _worker_setup() -> None:
    import cv2

    cv2.setNumThreads(1)


def _hash_frame(source, frame) -> tuple[str, str] | InputFileError:
    """(content hash, bytes hash) of the frame's image, or the error reading it. A source
    whose images are not files (a ROS bag) reads them itself: ``read_image(frame)`` ->
    (bytes, (H, W) uint8 image)."""
    try:
        read_image = getattr(source, "read_image", None)
        if read_image is not None:
            data, image = read_image(frame)
        else:
            data = read_bytes(frame.image_path, "image")
            image = decode_gray(data, frame.image_path)
        return content_hash(image), bytes_hash(data)
    except InputFileError as exc:
        return exc


def _build(
    source,
    frame,
    vocabulary: Vocabulary,
    vocabulary_id: int,
    config: IngestConfig,
    tags: tuple[str, ...],
) -> _Outcome:
    try:
        loaded = source.load(frame)
    except InputFileError as exc:
        images = (frame.image_path, getattr(frame, "right_image_path", None))
        kind = "image" if exc.path in images else getattr(source, "format", "")
        reason = {"image": "unreadable_image", "kitti": "unreadable_scan"}.get(
            kind, "unreadable_depth"
        )
        return _Outcome(frame, skip_reason=reason, error=exc)
    try:
        entry = build_entry(
            loaded.image_gray,
            content_hash(loaded.image_gray),
            frame.T_world_from_cam,
            loaded.source,
            source.intrinsics,
            vocabulary,
            vocabulary_id,
            config.build,
            tags=tags,
            timestamp_s=frame.timestamp_s,
        )
    except TooFewPointsError:
        return _Outcome(frame, skip_reason="too_few_points")
    except InvalidInputError as exc:
        return _Outcome(
            frame, skip_reason="bad_image", error=InputFileError(frame.image_path, str(exc))
        )
    return _Outcome(frame, entry=entry, raw_hash=bytes_hash(loaded.image_bytes))


class _Writer:
    """Commits batches of entries and the run's counters; feeds the live index."""

    def __init__(self, factory, map_id, run_id, registry, frames_total, skips) -> None:
        self.factory, self.map_id, self.run_id, self.registry = factory, map_id, run_id, registry
        self.frames_total = frames_total
        self.skips: dict[str, int] = dict(skips)
        self.frames_done = sum(skips.values())
        self.pending: list[tuple[NewEntry, str]] = []  # with the image's bytes hash
        self.points: list[int] = []
        self.added = 0  # by this attempt
        self.run_entries = 0  # the run's entries, earlier attempts included
        self.version = 0

    def already_added(self) -> None:
        """A frame whose entry an earlier attempt of this run committed: done and added."""
        self.frames_done += 1

    def skip(self, reason: str, n: int = 1) -> None:
        if n <= 0:
            return
        self.skips[reason] = self.skips.get(reason, 0) + n
        self.frames_done += n

    def commit(self, status: str | None = None, error: str | None = None) -> None:
        created = []
        with session_scope(self.factory) as session:
            for entry, raw_hash in self.pending:
                summary, was_created = entries_repo.add_entry(
                    session, self.map_id, entry, run_id=self.run_id, also_known_as=(raw_hash,)
                )
                if was_created:
                    created.append((summary.id, entry))
                else:
                    self.skips["duplicate_image"] = self.skips.get("duplicate_image", 0) + 1
            self.version = maps_repo.get_map(session, self.map_id).version
            self.run_entries = entries_repo.count_entries(session, self.map_id, run_id=self.run_id)
            runs_repo.update_run(
                session,
                self.run_id,
                status=status,
                frames_total=self.frames_total,
                frames_done=self.frames_done,
                entries_added=self.run_entries,
                frames_skipped=sum(self.skips.values()),
                skip_reasons=self.skips,
                error=error,
            )
        self.pending = []
        self.added += len(created)
        self.points.extend(len(e.points_cam) for _, e in created)
        if created and self.registry is not None:
            self.registry.entries_added(self.map_id)


def _load_vocabulary(factory, map_id: int, source) -> tuple[Vocabulary, int, dict | None]:
    with session_scope(factory) as session:
        record = maps_repo.get_map(session, map_id)
        vocab = maps_repo.get_vocabulary(session, record.vocabulary_id)
    if source.intrinsics != record.camera:
        # Entries are built with the source's own camera (their 3D points are metric, so
        # they stay valid); queries default to the map's camera.
        log.warning(
            "%s: camera %s differs from map %s's %s",
            source.name,
            source.intrinsics,
            record.name,
            record.camera,
        )
    vocabulary = Vocabulary.from_centres(np.asarray(vocab.centres), vocab.description)
    return vocabulary, vocab.id, record.features


_ABSENT = object()


def _new_frames(
    pool: ThreadPoolExecutor, source, frames: list, factory, map_id: int, writer, chunk: int
):
    """The frames whose image is not in the map yet, hashed
    ``chunk`` at a time (threads). The others are counted: as added if this run stored
    them (an earlier attempt), else as ``already_in_map``. A frame whose image cannot be
    read is passed on: the build stage reports it in order, by the run's bad-frame policy."""
    for lo in range(0, len(frames), chunk):
        part = frames[lo : lo + chunk]
        digests = list(pool.map(lambda frame: _hash_frame(source, frame), part))
        known = [h for d in digests if isinstance(d, tuple) for h in d]
        with session_scope(factory) as session:
            runs = entries_repo.runs_of_hashes(session, map_id, known) if known else {}
        for frame, digest in zip(part, digests, strict=True):
            if not isinstance(digest, tuple):
                yield frame
                continue
            owner = next((runs[h] for h in digest if h in runs), _ABSENT)
            if owner is _ABSENT:
                yield frame
            elif owner == writer.run_id:
                writer.already_added()
            else:
                writer.skip("already_in_map")


def ingest_run(
    session_factory: sessionmaker[Session],
    map_id: int,
    source,
    *,
    run_id: int,
    registry=None,
    tags: tuple[str, ...] = (),
    progress: Callable[[int, int], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    config: IngestConfig = IngestConfig(),
) -> IngestSummary:
    """Add the frames of ``source`` (a ``KittiSource``, ``TumSource`` or ``RosbagSource``) to
    map ``map_id`` as entries of run ``run_id`` (created by the caller). Idempotent and
    resumable (see the module docstring). ``progress(done, total)`` is called after every
    frame;
    ``should_stop()`` is polled between frames (True: commit what is built, mark the run
    interrupted, return). Raises InvalidInputError naming the file on bad input, after
    committing the entries of the frames before it and marking the run failed.
    """
    from threadpoolctl import threadpool_limits

    start = time.perf_counter()
    vocabulary, vocabulary_id, features = _load_vocabulary(session_factory, map_id, source)
    # entries described as the map's first ones were (maps.features)
    build = replace(config.build, orb=orb_for_rule(features, config.build.orb))
    config = replace(config, build=build)
    registration = None
    if config.register is not None:
        with threadpool_limits(1):
            source, correction = _register(
                session_factory, map_id, run_id, source, vocabulary, config, should_stop
            )
        registration = correction.summary()
    frames = list(source.frames)
    read_skips = dict(getattr(source, "read_skips", {}) or {})
    total = len(frames) + sum(read_skips.values())
    writer = _Writer(session_factory, map_id, run_id, registry, total, read_skips)
    with session_scope(session_factory) as session:
        runs_repo.update_run(
            session, run_id, status="running", frames_total=total, registration=registration
        )
    interrupted = False
    try:
        with (
            threadpool_limits(1),
            ThreadPoolExecutor(config.workers, initializer=_worker_setup) as pool,
        ):
            todo = _new_frames(
                pool, source, frames, session_factory, map_id, writer, config.hash_chunk
            )
            interrupted = _build_and_write(
                pool,
                source,
                todo,
                vocabulary,
                vocabulary_id,
                config,
                tuple(tags),
                writer,
                progress,
                should_stop,
            )
        writer.commit(status="interrupted" if interrupted else "done")
    except BaseException as exc:
        status = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
        try:
            writer.commit(status=status, error=str(exc) or type(exc).__name__)
        except Exception:  # the original error matters more than the bookkeeping
            log.exception("could not record the failure of run %s", run_id)
        raise
    if registry is not None:
        registry.persist(map_id)
    elapsed = time.perf_counter() - start
    done = writer.frames_done
    return IngestSummary(
        run_id=run_id,
        map_id=map_id,
        frames_total=total,
        frames_done=done,
        entries_added=writer.run_entries,
        frames_skipped=sum(writer.skips.values()),
        skip_reasons=dict(writer.skips),
        points_mean=float(np.mean(writer.points)) if writer.points else 0.0,
        points_min=int(min(writer.points)) if writer.points else 0,
        elapsed_s=elapsed,
        frames_per_s=done / elapsed if elapsed > 0 else 0.0,
        map_version=writer.version,
        interrupted=interrupted,
        registration=registration,
    )


def _register(session_factory, map_id, run_id, source, vocabulary, config, should_stop):
    """``source`` registered to the map's entries from other runs (an index of those
    within the search radius of the run's written path, built from the database, so a
    resumed run is registered to the same entries as before)."""
    index = RetrievalIndex()
    if source.frames:
        planar = planar_from_T_world_from_cam(np.stack([f.T_world_from_cam for f in source.frames]))
        r = config.register.search_radius_m
        box = (
            float(planar[:, 0].min() - r),
            float(planar[:, 0].max() + r),
            float(planar[:, 1].min() - r),
            float(planar[:, 1].max() + r),
        )
        with session_scope(session_factory) as session:
            batches = entries_repo.iter_map_vectors(
                session, map_id, exclude_run_id=run_id, within_m=box
            )
            for batch in batches:
                index.add(batch.entry_ids, batch.codes, batch.vlads, batch.planar)

    def lookup(ids) -> list[ReferenceEntry]:
        # an entry an operator deletes meanwhile is skipped, as the live index skips it
        with session_scope(session_factory) as session:
            rows = entries_repo.existing_entry_data(session, list(ids))
        return [ReferenceEntry.from_entry_data(r) for r in rows]

    rng = np.random.default_rng([map_id, run_id])
    target = RegistrationTarget(vocabulary, index, lookup)
    return register_source(
        source,
        target,
        rng,
        config=config.register,
        localize=LocalizeConfig(orb=config.build.orb),  # the map's rule (maps.features)
        should_stop=should_stop,
        workers=config.workers,
    )


def _build_and_write(
    pool, source, todo, vocabulary, vocabulary_id, config, tags, writer, progress, should_stop
) -> bool:
    """Run the build stage with a bounded window of futures; returns True if stopped."""
    window: deque[Future] = deque()
    max_in_flight = 2 * config.workers + 2
    frames = iter(todo)
    if progress is not None:
        progress(writer.frames_done, writer.frames_total)

    def refill() -> None:
        while len(window) < max_in_flight:
            frame = next(frames, None)
            if frame is None:
                return
            window.append(
                pool.submit(_build, source, frame, vocabulary, vocabulary_id, config, tags)
            )

    refill()
    try:
        while window:
            if should_stop is not None and should_stop():
                return True
            outcome: _Outcome = window.popleft().result()
            refill()
            if outcome.error is not None and not config.skip_bad_frames:
                raise outcome.error
            if outcome.entry is not None:
                writer.pending.append((outcome.entry, outcome.raw_hash))
                writer.frames_done += 1
            else:
                writer.skip(outcome.skip_reason or "skipped")
            if len(writer.pending) >= config.batch_size:
                writer.commit()
            if progress is not None:
                progress(writer.frames_done, writer.frames_total)
        return False
    finally:
        for future in window:
            future.cancel()

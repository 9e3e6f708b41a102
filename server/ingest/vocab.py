"""A map's own vocabulary: train one from a run's images, and switch a map to it.

Which descriptors a VLAD is computed from: an entry's VLAD is computed from *all* ORB
descriptors of its image, exactly like a query's (``monoloc.server.entry_builder``), while the
entry stores only the descriptors of keypoints that received a 3D point. Measured on a
sim city (100 query frames against 100 map frames, full KITTI resolution): recall@1
0.97 with whole-image map VLADs against 0.76 when map VLADs use only the 3D keypoints'
descriptors (the LiDAR sees nothing above +2 deg, so facades' upper parts drop out).

So a vocabulary change recomputes each VLAD from the entry's original image whenever
it can: the map's runs record where they were read from, the image is found again by
its sha256 (so a changed file is never used), and its ORB descriptors are recomputed.
Entries whose image is no longer available (moved data, single uploaded images) fall
back to their stored descriptors (the 3D keypoints' only: an approximation, counted
in the result as ``approximate``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from monoloc.core.errors import InvalidInputError, MonolocError
from monoloc.server.ingest.common import bytes_hash, content_hash, decode_gray, read_bytes
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage import runs as runs_repo
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.records import VocabularyRecord
from monoloc.server.vision.features import OrbConfig, extract_features, orb_for_rule
from monoloc.server.vision.vocabulary import Vocabulary, VocabularyConfig, train_vocabulary

log = logging.getLogger(__name__)

DEFAULT_TRAINING_IMAGES = 300
_BATCH = 64


def _features_of(source, frame, orb: OrbConfig) -> np.ndarray:
    read_image = getattr(source, "read_image", None)  # a ROS bag's images are messages
    if read_image is not None:
        image = read_image(frame)[1]
    else:
        image = decode_gray(read_bytes(frame.image_path, "image"), frame.image_path)
    return extract_features(image, orb).descriptors


def training_descriptors(
    source,
    max_images: int = DEFAULT_TRAINING_IMAGES,
    orb: OrbConfig = OrbConfig(),
    workers: int = 2,
) -> tuple[np.ndarray, int]:
    """ORB descriptors (N, 32) uint8 of up to ``max_images`` frames evenly spread over the
    source, and the number of images used."""
    import cv2
    from threadpoolctl import threadpool_limits

    frames = list(source.frames)
    if not frames:
        raise InvalidInputError(f"{source.name}: no frames to train a vocabulary on")
    picks = np.unique(np.linspace(0, len(frames) - 1, min(max_images, len(frames))).astype(int))
    cv2.setNumThreads(1)
    with threadpool_limits(1), ThreadPoolExecutor(workers) as pool:
        sets = list(pool.map(lambda i: _features_of(source, frames[i], orb), picks))
    return np.concatenate(sets), len(picks)


def train_map_vocabulary(
    session_factory: sessionmaker[Session],
    source,
    config: VocabularyConfig = VocabularyConfig(),
    *,
    max_images: int = DEFAULT_TRAINING_IMAGES,
    orb: OrbConfig = OrbConfig(),
) -> VocabularyRecord:
    """k-means vocabulary (k = ``config.n_words``, FAISS) of ORB descriptors from a run's
    images (``max_images`` spread evenly; descriptors subsampled to
    ``config.max_descriptors`` if set), stored (or found, same centres) in the database."""
    descriptors, n_images = training_descriptors(source, max_images, orb)
    used = min(len(descriptors), config.max_descriptors or len(descriptors))
    description = (
        f"k-means (FAISS, k={config.n_words}, {config.n_iter} iterations, seed {config.seed}) "
        f"on {used} ORB descriptors (blur {orb.blur_ksize}, max {orb.max_features} per image) "
        f"of {n_images} of {len(source.frames)} images of {source.format} run {source.name}"
    )
    vocabulary = train_vocabulary(descriptors, config, description)
    with session_scope(session_factory) as session:
        record, _ = maps_repo.get_or_create_vocabulary(session, vocabulary.centres, description)
    return record


@dataclass(frozen=True)
class VocabularyChange:
    """Entries recomputed (``exact``: from their image; ``approximate``: from the stored
    3D keypoints' descriptors), whether the job was stopped early, the final version."""

    map_id: int
    vocabulary_id: int
    recomputed: int
    exact: int
    approximate: int
    stopped: bool
    map_version: int


def _reopen(source_format: str, source_name: str):
    from monoloc.server.ingest.sources import read_tum_run

    path = Path(source_name)
    if not source_name or not path.is_dir():
        return None
    try:
        if source_format == "kitti":
            return _reopen_kitti(path)
        if source_format == "tum":
            return read_tum_run(path, camera="default")  # intrinsics unused here
    except MonolocError as exc:
        log.info("run source %s cannot be reopened: %s", source_name, exc)
    return None


def _reopen_kitti(path: Path):
    """Only the images are read again: a run mapped from stereo may have no scans."""
    from monoloc.server.ingest.sources import read_kitti_sequence

    try:
        return read_kitti_sequence(path)
    except MonolocError:
        return read_kitti_sequence(path, depth_from="stereo")


def _image_paths_by_hash(session_factory, map_id: int) -> dict[str, Path]:
    with session_scope(session_factory) as session:
        runs = runs_repo.list_runs(session, map_id)
    paths: dict[str, Path] = {}
    for run in runs:
        source = _reopen(run.source_format, run.source_name)
        if source is None:
            continue
        for frame in source.frames:
            try:
                data = read_bytes(frame.image_path, "image")
                digests = (content_hash(decode_gray(data, frame.image_path)), bytes_hash(data))
            except MonolocError:
                continue
            for digest in digests:  # entries are known by either (see common.content_hash)
                paths.setdefault(digest, frame.image_path)
    return paths


def _pending_ids(session_factory, map_id: int, vocabulary_id: int) -> list[int]:
    ids, offset = [], 0
    with session_scope(session_factory) as session:
        while True:
            page = entries_repo.list_entries(session, map_id, limit=1000, offset=offset)
            ids.extend(e.id for e in page if e.vocabulary_id != vocabulary_id)
            if len(page) < 1000:
                return ids
            offset += 1000


def _descriptor_set(entry, paths: dict[str, Path], orb: OrbConfig) -> tuple[np.ndarray, bool]:
    path = paths.get(entry.summary.source_image_hash)
    if path is not None:
        try:
            data = read_bytes(path, "image")
            image = decode_gray(data, path)
            if entry.summary.source_image_hash in (content_hash(image), bytes_hash(data)):
                return extract_features(image, orb).descriptors, True
        except MonolocError:
            pass
    return np.asarray(entry.descriptors), False


def change_map_vocabulary_detailed(
    session_factory: sessionmaker[Session],
    map_id: int,
    vocabulary_id: int,
    *,
    registry=None,
    progress: Callable[[int, int], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    orb: OrbConfig = OrbConfig(),
) -> VocabularyChange:
    """Point the map at ``vocabulary_id`` and recompute every entry's VLAD and code with it
    (see the module docstring for which descriptors). Resumable: entries already on the
    new vocabulary are skipped, so a stopped or failed job is simply run again. Commits
    per batch; the registry forgets the map at the end (its index is rebuilt on next use).
    """
    import cv2
    from threadpoolctl import threadpool_limits

    from monoloc.server.vision.binary_code import vlad_binary_code
    from monoloc.server.vision.vlad import compute_vlad

    with session_scope(session_factory) as session:
        record = maps_repo.get_map(session, map_id)
        vocab = maps_repo.get_vocabulary(session, vocabulary_id)
        if record.vocabulary_id != vocabulary_id:
            maps_repo.set_map_vocabulary(session, map_id, vocabulary_id)
    vocabulary = Vocabulary.from_centres(np.asarray(vocab.centres), vocab.description)
    orb = orb_for_rule(record.features, orb)  # described as its entries were (maps.features)
    todo = _pending_ids(session_factory, map_id, vocabulary_id)
    paths = _image_paths_by_hash(session_factory, map_id) if todo else {}
    exact = approximate = 0
    stopped = False
    cv2.setNumThreads(1)
    with threadpool_limits(1), ThreadPoolExecutor(2) as pool:
        for lo in range(0, len(todo), _BATCH):
            if should_stop is not None and should_stop():
                stopped = True
                break
            with session_scope(session_factory) as session:
                batch = entries_repo.get_entry_data(session, todo[lo : lo + _BATCH])
            sets = list(pool.map(lambda e: _descriptor_set(e, paths, orb), batch))
            with session_scope(session_factory) as session:
                for entry, (descriptors, from_image) in zip(batch, sets, strict=True):
                    vlad = compute_vlad(descriptors, vocabulary)
                    entries_repo.update_entry_vlad(
                        session,
                        entry.id,
                        vlad=vlad,
                        code=vlad_binary_code(vlad),
                        vocabulary_id=vocabulary_id,
                    )
                    exact += from_image
                    approximate += not from_image
            if progress is not None:
                progress(min(lo + _BATCH, len(todo)), len(todo))
    with session_scope(session_factory) as session:
        version = maps_repo.get_map(session, map_id).version
    if registry is not None:
        registry.forget(map_id, delete_file=True)
    return VocabularyChange(
        map_id, vocabulary_id, exact + approximate, exact, approximate, stopped, version
    )

"""Entries are identified by their decoded image, not their file's bytes: the same PNG
with bytes appended, or re-encoded, is not stored twice (issue 15, item 8), and maps
stored before this rule (entries known by the sha256 of their bytes) keep refusing
their duplicates."""

from __future__ import annotations

import hashlib

import cv2
import numpy as np
from sqlalchemy import update

from monoloc.server.ingest.common import bytes_hash, content_hash
from monoloc.server.ingest.pipeline import ingest_run
from monoloc.server.ingest.single import add_single_image
from monoloc.server.ingest.sources import read_kitti_sequence
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.models import Entry


def _n_entries(factory, map_id: int) -> int:
    with session_scope(factory) as session:
        return entries_repo.count_entries(session, map_id)


def _as_legacy_map(factory, map_id: int, sequence) -> None:
    """Rewrite every entry's hash to the sha256 of its file's bytes, as a database written
    before content hashing holds them."""
    by_content = {}
    for frame in sequence.frames:
        data = frame.image_path.read_bytes()
        by_content[content_hash(sequence.load(frame).image_gray)] = bytes_hash(data)
    with session_scope(factory) as session:
        for new, old in by_content.items():
            session.execute(
                update(Entry)
                .where(Entry.map_id == map_id, Entry.source_image_hash == new)
                .values(source_image_hash=old)
            )


def test_content_hash_ignores_the_encoding_but_not_the_pixels():
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (70, 90), dtype=np.uint8)
    assert content_hash(image) == content_hash(image.copy())
    assert content_hash(image) != content_hash(image.T.copy())  # same pixels, other shape
    changed = image.copy()
    changed[5, 7] ^= 1
    assert content_hash(image) != content_hash(changed)
    png = cv2.imencode(".png", image)[1].tobytes()
    assert content_hash(image) != hashlib.sha256(png).hexdigest() != bytes_hash(png + b"x")


def test_same_png_with_bytes_appended_is_not_stored_twice(kitti_root, factory, make_map):
    seq = read_kitti_sequence(kitti_root.root)
    map_id = make_map()
    frame = seq.frames[3]
    data = frame.image_path.read_bytes()
    source = seq.load(frame).source
    first, created = add_single_image(factory, map_id, data, frame.T_world_from_cam, source)
    assert created
    for variant in (data + b"\x00" * 100, data + b"trailing junk after IEND"):
        again, created = add_single_image(factory, map_id, variant, frame.T_world_from_cam, source)
        assert not created and again.id == first.id
    reencoded = cv2.imencode(".png", seq.load(frame).image_gray, [cv2.IMWRITE_PNG_COMPRESSION, 0])
    again, created = add_single_image(
        factory, map_id, reencoded[1].tobytes(), frame.T_world_from_cam, source
    )
    assert not created and again.id == first.id
    assert _n_entries(factory, map_id) == 1


def test_run_with_bytes_appended_to_every_image_adds_nothing(
    kitti_root, kitti_copy, factory, make_map, make_run
):
    seq = read_kitti_sequence(kitti_root.root)
    map_id = make_map()
    ingest_run(factory, map_id, seq, run_id=make_run(map_id, seq))
    for frame in read_kitti_sequence(kitti_copy.root).frames:
        with open(frame.image_path, "ab") as out:
            out.write(b"appended bytes")
    padded = read_kitti_sequence(kitti_copy.root)
    second = ingest_run(factory, map_id, padded, run_id=make_run(map_id, padded))
    assert second.entries_added == 0 and second.skip_reasons == {"already_in_map": 8}
    assert _n_entries(factory, map_id) == 8


def test_map_stored_with_byte_hashes_keeps_refusing_duplicates(
    kitti_root, factory, make_map, make_run
):
    seq = read_kitti_sequence(kitti_root.root)
    map_id = make_map()
    ingest_run(factory, map_id, seq, run_id=make_run(map_id, seq))
    _as_legacy_map(factory, map_id, seq)
    again = ingest_run(factory, map_id, seq, run_id=make_run(map_id, seq))
    assert again.entries_added == 0 and again.skip_reasons == {"already_in_map": 8}
    frame = seq.frames[0]
    data = frame.image_path.read_bytes()
    summary, created = add_single_image(
        factory, map_id, data, frame.T_world_from_cam, seq.load(frame).source
    )
    assert not created and summary.source_image_hash == bytes_hash(data)
    assert _n_entries(factory, map_id) == 8


def test_resumed_run_of_a_legacy_map_counts_its_own_entries_as_added(
    kitti_root, factory, make_map, make_run
):
    seq = read_kitti_sequence(kitti_root.root)
    map_id = make_map()
    run_id = make_run(map_id, seq)
    ingest_run(factory, map_id, seq, run_id=run_id)
    _as_legacy_map(factory, map_id, seq)
    resumed = ingest_run(factory, map_id, seq, run_id=run_id)
    assert (resumed.entries_added, resumed.frames_skipped, resumed.frames_total) == (8, 0, 8)

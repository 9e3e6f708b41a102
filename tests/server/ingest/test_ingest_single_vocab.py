"""Single reference images, and a map's own vocabulary (train, then change)."""

from __future__ import annotations

import numpy as np
import pytest

from monoloc.core.errors import InvalidInputError
from monoloc.server.entry_builder import DepthSource
from monoloc.server.ingest.pipeline import ingest_run
from monoloc.server.ingest.single import add_single_image, transform_from_numbers
from monoloc.server.ingest.sources import read_kitti_sequence
from monoloc.server.ingest.vocab import change_map_vocabulary_detailed, train_map_vocabulary
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage.db import session_scope
from monoloc.server.vision.features import extract_features
from monoloc.server.vision.vlad import compute_vlad
from monoloc.server.vision.vocabulary import Vocabulary, VocabularyConfig


def test_single_image_with_lidar_then_depth(kitti_root, factory, make_map):
    seq = read_kitti_sequence(kitti_root.root)
    map_id = make_map()
    frame = seq.frames[2]
    data = frame.image_path.read_bytes()
    loaded = seq.load(frame)
    summary, created = add_single_image(
        factory, map_id, data, frame.T_world_from_cam, loaded.source, tags=("manual",)
    )
    assert created and summary.n_points > 300 and summary.tags == ("manual",)
    again, created_again = add_single_image(
        factory, map_id, data, frame.T_world_from_cam, loaded.source
    )
    assert not created_again and again.id == summary.id
    # The same view with a depth image instead (constant 7.8 m: camera z = 0.2 at frame 2,
    # the frame is yawed, so this is only roughly the wall: enough for an entry).
    depth = DepthSource(np.full((188, 620), 7.8 * 5000, dtype=np.uint16), 5000.0)
    other = np.roll(loaded.image_gray, 1, axis=0)
    import cv2

    png = cv2.imencode(".png", other)[1].tobytes()
    by_depth, created = add_single_image(factory, map_id, png, frame.T_world_from_cam, depth)
    assert created and by_depth.id != summary.id
    with pytest.raises(InvalidInputError, match="not a valid PNG/JPEG"):
        add_single_image(factory, map_id, b"junk", frame.T_world_from_cam, depth)
    with pytest.raises(InvalidInputError, match="12 .3x4. or 16"):
        transform_from_numbers(np.arange(9.0), "--pose")


def test_train_and_change_vocabulary(kitti_root, factory, make_map, make_run, settings):
    from monoloc.server.map_registry import MapRegistry

    seq = read_kitti_sequence(kitti_root.root)
    map_id = make_map()
    ingest_run(factory, map_id, seq, run_id=make_run(map_id, seq))
    record = train_map_vocabulary(factory, seq, VocabularyConfig(n_iter=5))
    assert record.n_words == 64 and "8 of 8 images of kitti run" in record.description
    registry = MapRegistry(factory, settings.index_dir)
    old_vocabulary_hash = registry.get(map_id).vocabulary.version
    change = change_map_vocabulary_detailed(factory, map_id, record.id, registry=registry)
    assert (change.recomputed, change.exact, change.approximate) == (8, 8, 0)
    new = Vocabulary.from_centres(np.asarray(record.centres))
    assert registry.get(map_id).vocabulary.version == new.version != old_vocabulary_hash
    with session_scope(factory) as session:
        assert maps_repo.get_map(session, map_id).vocabulary_id == record.id
        entries = entries_repo.get_entry_data(
            session, [e.id for e in entries_repo.list_entries(session, map_id)]
        )
    assert all(e.summary.vocabulary_id == record.id for e in entries)
    # Exact: the VLAD of the whole image with the new vocabulary, as at query time.
    by_time = {round(e.summary.timestamp_s, 3): e for e in entries}
    image = seq.load(seq.frames[3]).image_gray
    expected = compute_vlad(extract_features(image).descriptors, new)
    np.testing.assert_allclose(by_time[0.3].vlad, expected, atol=1e-6)
    # Running it again has nothing left to do.
    assert change_map_vocabulary_detailed(factory, map_id, record.id).recomputed == 0


def test_vocabulary_change_without_the_images_uses_stored_descriptors(
    kitti_copy, factory, make_map, make_run
):
    import shutil

    seq = read_kitti_sequence(kitti_copy.root)
    map_id = make_map()
    ingest_run(factory, map_id, seq, run_id=make_run(map_id, seq))
    record = train_map_vocabulary(factory, seq, VocabularyConfig(n_iter=5, seed=1))
    shutil.rmtree(kitti_copy.root)  # the recording is gone
    change = change_map_vocabulary_detailed(factory, map_id, record.id)
    assert (change.exact, change.approximate) == (0, 8)
    with session_scope(factory) as session:
        entry = entries_repo.get_entry_data(
            session, [entries_repo.list_entries(session, map_id, limit=1)[0].id]
        )[0]
    new = Vocabulary.from_centres(np.asarray(record.centres))
    np.testing.assert_allclose(entry.vlad, compute_vlad(entry.descriptors, new), atol=1e-6)


def _png_declaring(width_px: int, height_px: int, bit_depth: int, colour_type: int) -> bytes:
    """A valid PNG of ``width_px`` x ``height_px`` whose pixels are all zero: zlib packs the
    zero rows of even a 5000 x 5000 16-bit RGBA image (200 MB decoded) into ~200 KB."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(kind + data) & 0xFFFFFFFF
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    channels = {0: 1, 2: 3, 4: 2, 6: 4}[colour_type]
    row = b"\x00" * (1 + width_px * channels * bit_depth // 8)  # filter byte + pixels
    packer = zlib.compressobj(9)
    idat = b"".join(packer.compress(row) for _ in range(height_px)) + packer.flush()
    ihdr = struct.pack(">IIBBBBB", width_px, height_px, bit_depth, colour_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def test_an_entry_of_the_wrong_declared_size_is_refused_before_decoding(
    kitti_root, factory, make_map, monkeypatch
):
    """Issue 15.4: a 5000 x 5000 16-bit RGBA PNG of ~200 KB decoded to ~474 MB before its
    size was checked. The declared size is refused first: the decoder is never called."""
    import monoloc.server.ingest.single as single

    decoded = []
    real_decode = single.decode_gray
    monkeypatch.setattr(
        single, "decode_gray", lambda *a, **k: decoded.append(1) or real_decode(*a, **k)
    )
    seq = read_kitti_sequence(kitti_root.root)
    map_id = make_map()
    frame = seq.frames[2]
    loaded = seq.load(frame)
    bomb = _png_declaring(5000, 5000, 16, 6)
    assert len(bomb) < 1_000_000
    with pytest.raises(InvalidInputError, match="image is 5000x5000 pixels; the camera is"):
        add_single_image(factory, map_id, bomb, frame.T_world_from_cam, loaded.source)
    assert decoded == []
    # The spy does see the decode of an image of the right size.
    add_single_image(
        factory, map_id, frame.image_path.read_bytes(), frame.T_world_from_cam, loaded.source
    )
    assert decoded == [1]

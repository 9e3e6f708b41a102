"""Index files written by a removed index kind (FAISS HNSW or IVF: format 1 with a
serialised FAISS index) are refused with a clear message, and the server rebuilds such a
map from the database on start; its new file loads as it is afterwards."""

from __future__ import annotations

import hashlib
import logging

import numpy as np
import pytest

from monoloc.core.camera import KITTI_CAM0
from monoloc.core.geometry import T_world_from_cam_planar
from monoloc.server.index.persist import IndexFileError, load_index, vlad_files
from monoloc.server.index.sketch import vlad_sketch
from monoloc.server.map_registry import MapRegistry
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.maps import create_map, get_or_create_vocabulary
from monoloc.server.storage.records import NewEntry
from monoloc.server.vision.binary_code import vlad_binary_code

N_ENTRIES = 40


def _unit_vlads(n: int) -> tuple[np.ndarray, np.random.Generator]:
    rng = np.random.default_rng(0)
    vlads = rng.normal(size=(n, 2048)).astype(np.float32)
    return vlads / np.linalg.norm(vlads, axis=1, keepdims=True), rng


def write_removed_kind_file(path, ids, codes, vlads, poses, map_version: int, kind: str) -> None:
    """An index file as the HNSW and IVF kinds wrote it (format 1): the arrays plus the
    serialised FAISS index under ``faiss_large``."""
    import faiss

    if kind == "hnsw":
        large = faiss.IndexBinaryIDMap2(faiss.IndexBinaryHNSW(2048, 32))
    else:
        large = faiss.IndexBinaryIVF(faiss.IndexBinaryFlat(2048), 2048, 16)
        large.train(codes)
    large.add_with_ids(codes, np.asarray(ids, dtype=np.int64))
    np.savez(
        path,
        ids=np.asarray(ids, dtype=np.int64),
        codes=codes,
        vlads=np.asarray(vlads, dtype=np.float32),
        poses=np.asarray(poses, dtype=np.float64),
        sketches=vlad_sketch(vlads),
        map_version=np.array(map_version, dtype=np.int64),
        format_version=np.array(1, dtype=np.int64),
        faiss_large=faiss.serialize_index_binary(large),
    )


@pytest.mark.parametrize("kind", ["hnsw", "ivf"])
def test_a_file_of_a_removed_index_kind_is_refused_clearly(tmp_path, kind):
    vlads, _ = _unit_vlads(300)
    poses = np.zeros((300, 3))
    path = tmp_path / "map_1.index.npz"
    write_removed_kind_file(path, np.arange(300), vlad_binary_code(vlads), vlads, poses, 4, kind)
    with pytest.raises(IndexFileError, match="holds a FAISS HNSW or IVF index"):
        load_index(path, expected_map_version=4)


def _map_with_entries(factory) -> tuple[int, np.ndarray]:
    """A map of N_ENTRIES entries along a line; returns its id and their VLADs."""
    vlads, rng = _unit_vlads(N_ENTRIES)
    centres = rng.uniform(0, 255, (64, 32)).astype(np.float32)
    with session_scope(factory) as session:
        vocab, _ = get_or_create_vocabulary(session, centres, "test vocabulary")
        map_id = create_map(session, "m", KITTI_CAM0, vocab.id).id
        for i, vlad in enumerate(vlads):
            entry = NewEntry(
                source_image_hash=hashlib.sha256(f"frame {i}".encode()).hexdigest(),
                T_world_from_cam=T_world_from_cam_planar(2.0 * i, 0.0, 0.0, height_m=1.6),
                vlad=vlad,
                code=vlad_binary_code(vlad),
                keypoints_px=rng.uniform(0, 370, (20, 2)).astype(np.float32),
                descriptors=rng.integers(0, 256, (20, 32), dtype=np.uint8),
                points_cam=rng.uniform(1, 40, (20, 3)).astype(np.float32),
                image_width_px=KITTI_CAM0.width_px,
                image_height_px=KITTI_CAM0.height_px,
            )
            entries_repo.add_entry(session, map_id, entry)
    return map_id, vlads


def test_an_index_file_of_a_removed_kind_is_rebuilt_from_the_database(factory, settings, caplog):
    map_id, vlads = _map_with_entries(factory)
    registry = MapRegistry(factory, settings.index_dir)
    runtime = registry.get(map_id)  # builds and writes the current file
    path = registry.index_path(map_id)
    with np.load(path) as current:
        arrays = {name: current[name] for name in current.files}
    path.unlink()
    write_removed_kind_file(
        path,
        arrays["ids"],
        arrays["codes"],
        runtime.index.snapshot()["vlads"],  # format 2 keeps them in the float file
        arrays["poses"],
        int(arrays["map_version"]),
        "hnsw",
    )
    caplog.set_level(logging.INFO, logger="monoloc.server.map_registry")
    restarted = MapRegistry(factory, settings.index_dir).get(map_id)
    assert "holds a FAISS HNSW or IVF index" in caplog.text
    assert "rebuilding from the database" in caplog.text
    assert restarted.index.kind == "flat" and len(restarted.index) == N_ENTRIES
    query = restarted.index.search(vlads[7], vlad_binary_code(vlads[7]), k=3)
    expected = runtime.index.search(vlads[7], vlad_binary_code(vlads[7]), k=3)
    np.testing.assert_array_equal(query.entry_ids, expected.entry_ids)
    with np.load(path) as rewritten:
        assert "faiss_large" not in rewritten.files and "vlads" not in rewritten.files
    (vlad_file,) = vlad_files(path)  # one float file: the first build's went with the rebuild
    assert np.array_equal(np.load(vlad_file), runtime.index.snapshot()["vlads"])
    caplog.clear()
    MapRegistry(factory, settings.index_dir).get(map_id)
    assert "index loaded from" in caplog.text and "rebuilding" not in caplog.text


def test_a_replica_moves_live_adds_to_its_file_past_the_limit(factory, settings, monkeypatch):
    """Catching up past UNPERSISTED_MAX live adds rewrites the map's index files: the
    float VLADs leave memory and a restart loads the new file as it is."""
    import monoloc.server.map_registry as registry_module

    map_id, vlads = _map_with_entries(factory)
    registry = MapRegistry(factory, settings.index_dir)
    runtime = registry.get(map_id)
    monkeypatch.setattr(registry_module, "UNPERSISTED_MAX", 2)
    new_vlads, rng = _unit_vlads(N_ENTRIES + 3)
    held = []
    for i, vlad in enumerate(new_vlads[N_ENTRIES:], start=N_ENTRIES):
        with session_scope(factory) as session:
            entry = NewEntry(
                source_image_hash=hashlib.sha256(f"late frame {i}".encode()).hexdigest(),
                T_world_from_cam=T_world_from_cam_planar(2.0 * i, 0.0, 0.0, height_m=1.6),
                vlad=vlad,
                code=vlad_binary_code(vlad),
                keypoints_px=rng.uniform(0, 370, (20, 2)).astype(np.float32),
                descriptors=rng.integers(0, 256, (20, 32), dtype=np.uint8),
                points_cam=rng.uniform(1, 40, (20, 3)).astype(np.float32),
                image_width_px=KITTI_CAM0.width_px,
                image_height_px=KITTI_CAM0.height_px,
            )
            entries_repo.add_entry(session, map_id, entry)
        runtime = registry.catch_up(map_id)
        held.append(runtime.index.unpersisted)
    assert held == [1, 0, 1]  # the second add reached the limit: the file was rewritten
    assert len(runtime.index) == N_ENTRIES + 3
    late = new_vlads[N_ENTRIES + 1]
    found = runtime.index.search(late, vlad_binary_code(late), k=1)
    assert found.distances[0] < 1e-5
    restarted = load_index(registry.index_path(map_id), runtime.version - 1)
    assert restarted.search(late, vlad_binary_code(late), k=1).entry_ids[0] == found.entry_ids[0]

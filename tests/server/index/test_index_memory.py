"""The index without float VLADs in its own memory: 4-bit re-rank, exact distances read
on demand from the float file, live adds in a delta until persisted."""

import numpy as np
import pytest

from monoloc.core.prior import RetrievalPrior
from monoloc.server.index.compressed import (
    compress_vlads,
    compressed_sq_distances,
    vlad_quantizer,
)
from monoloc.server.index.persist import (
    IndexFileError,
    load_index,
    rebuild_index,
    save_index,
    vlad_files,
)
from monoloc.server.index.retrieval import IndexConfig, RetrievalIndex
from monoloc.server.index.vlad_store import VladFile
from monoloc.server.storage.entries import MapVectors
from monoloc.server.vision.binary_code import vlad_binary_code


def _route(rng, n):
    protos = np.empty((n, 2048), dtype=np.float32)
    p = rng.normal(size=2048).astype(np.float32)
    for i in range(n):
        p = 0.9 * p + np.sqrt(1 - 0.81) * rng.normal(size=2048).astype(np.float32)
        protos[i] = p
    views = protos + 0.6 * rng.normal(size=protos.shape).astype(np.float32)
    return views / np.linalg.norm(views, axis=1, keepdims=True)


def _map(n, seed=0):
    rng = np.random.default_rng(seed)
    vlads = _route(rng, n)
    poses = np.zeros((n, 3))
    poses[:, 0] = np.arange(n) * 1.0
    return vlads, vlad_binary_code(vlads), poses, rng


def _noisy(rng, vlad):
    q = vlad + 0.3 * rng.normal(size=2048).astype(np.float32) / np.sqrt(2048)
    return (q / np.linalg.norm(q)).astype(np.float32)


class _CountingReads:
    """Counts the float VLAD rows an index reads from its store."""

    def __init__(self, index):
        self.rows, store = 0, index._store
        gather = store.gather

        def counted(refs):
            self.rows += len(refs)
            return gather(refs)

        store.gather = counted


def test_the_4bit_distances_are_faiss_decoded_distances():
    rng = np.random.default_rng(0)
    vlads = rng.normal(size=(50, 2048)).astype(np.float32) * 0.03
    vlads[0, :5] = [0.5, -0.5, 0.124, -0.124, 0.0]  # two clipped, two near the range's end
    compressed = compress_vlads(vlads)
    assert compressed.shape == (50, 1024) and compressed.dtype == np.uint8
    query = rng.normal(size=2048).astype(np.float32) * 0.03
    rows = np.array([3, 0, 49, 3])
    decoded = vlad_quantizer().decode(compressed[rows])
    expected = ((decoded.astype(np.float64) - query) ** 2).sum(axis=1)
    np.testing.assert_allclose(compressed_sq_distances(query, compressed, rows), expected, 1e-5)
    assert abs(decoded[1, 0] - 0.125) < 0.01 and abs(decoded[1, 1] + 0.125) < 0.01


@pytest.mark.parametrize("scan", [False, True])
def test_distances_are_exact_and_few_float_rows_are_read(scan):
    vlads, codes, poses, rng = _map(3000)
    config = IndexConfig(scan_min_entries=1000 if scan else 50_000)
    index = RetrievalIndex.from_arrays(np.arange(3000), codes, vlads, poses, config)
    assert index.kind == ("scan" if scan else "flat")
    reads = _CountingReads(index)
    recalls = []
    for i in rng.choice(3000, 30, replace=False):
        q = _noisy(rng, vlads[i])
        prior = RetrievalPrior(x_m=float(i), y_m=0.0, radius_m=1500.0) if i % 2 else None
        before = reads.rows
        res = index.search(q, vlad_binary_code(q), k=10, prior=prior)
        assert reads.rows - before <= 10 + config.exact_margin
        exact = np.linalg.norm(vlads[res.entry_ids].astype(np.float64) - q, axis=1)
        np.testing.assert_allclose(res.distances, exact, atol=1e-6)
        candidates = np.arange(3000)
        if prior is not None:
            assert np.all(np.abs(poses[res.entry_ids, 0] - i) <= 1500.0)
            candidates = candidates[np.abs(poses[:, 0] - i) <= 1500.0]
        d = np.linalg.norm(vlads[candidates] - q, axis=1)
        truth = set(candidates[np.argsort(d)[:10]].tolist())
        recalls.append(len(truth & set(res.entry_ids.tolist())) / 10)
    assert np.mean(recalls) >= 0.95


def test_a_loaded_index_reads_its_float_vlads_from_the_file(tmp_path):
    vlads, codes, poses, rng = _map(600, seed=1)
    config = IndexConfig(scan_min_entries=500)
    index = RetrievalIndex.from_arrays(np.arange(600), codes, vlads, poses, config)
    assert np.shares_memory(index._store.base, vlads)  # handed over, not copied
    path = tmp_path / "map_1.index.npz"
    save_index(path, index, 5)
    with np.load(path) as data:
        assert "vlads" not in data.files and data["compressed"].shape == (600, 1024)
    (vlad_file,) = vlad_files(path)
    loaded = load_index(path, 5, config)
    assert isinstance(loaded._store.base, VladFile) and loaded._store.base.path == vlad_file
    assert loaded.kind == "scan" and loaded.unpersisted == 0
    np.testing.assert_array_equal(loaded.vlads_at(np.array([7, 599])), vlads[[7, 599]])
    # Live adds stay in memory (replacing id 3 too) until the next save moves them out.
    extra, extra_codes, extra_poses, _ = _map(20, seed=2)
    loaded.add(np.arange(600, 620), extra_codes, extra, extra_poses)
    loaded.add([3], extra_codes[:1] ^ 0xFF, -vlads[3:4], poses[3:4])
    assert 3 in loaded and 620 not in loaded and loaded.unpersisted == 21
    assert loaded.search(extra[5], extra_codes[5], k=1).entry_ids[0] == 605
    loaded.remove([605, 10])
    save_index(path, loaded, 6)
    assert loaded.unpersisted == 0 and vlad_files(path) != [vlad_file]
    again = load_index(path, 6, config)
    assert len(again) == 618 and 605 not in again and 10 not in again
    for index_ in (loaded, again):
        q = _noisy(rng, extra[7])
        res = index_.search(q, vlad_binary_code(q), k=3)
        assert res.entry_ids[0] == 607
        np.testing.assert_allclose(res.distances[0], np.linalg.norm(extra[7] - q), atol=1e-6)
        res = index_.search(-vlads[3], extra_codes[0] ^ 0xFF, k=1)
        assert res.entry_ids[0] == 3 and res.distances[0] < 1e-5


def test_an_edit_during_a_save_keeps_the_delta(tmp_path):
    vlads, codes, poses, _ = _map(100, seed=3)
    index = RetrievalIndex()
    index.add(np.arange(50), codes[:50], vlads[:50], poses[:50])
    arrays, blocks, edits = index.persist_state()
    index.add(np.arange(50, 100), codes[50:], vlads[50:], poses[50:])  # after the snapshot
    from monoloc.server.index.persist import map_vlads, write_index_files

    vlad_path = write_index_files(tmp_path / "i.npz", arrays, blocks, 1)
    assert not index.adopt_vlads(map_vlads(vlad_path), edits)
    assert index.unpersisted == 100 and len(load_index(tmp_path / "i.npz", 1)) == 50
    assert index.search(vlads[77], codes[77], k=1).entry_ids[0] == 77


def test_damaged_or_old_float_files_are_refused(tmp_path):
    vlads, codes, poses, _ = _map(40, seed=4)
    path = tmp_path / "map_1.index.npz"
    save_index(path, RetrievalIndex.from_arrays(np.arange(40), codes, vlads, poses), 2)
    (vlad_file,) = vlad_files(path)
    raw = bytearray(vlad_file.read_bytes())
    raw[-5000] ^= 0x10  # one bit of one VLAD value
    vlad_file.write_bytes(bytes(raw))
    with pytest.raises(IndexFileError, match="CRC-32"):
        load_index(path, 2)
    vlad_file.write_bytes(bytes(raw[: len(raw) // 2]))
    with pytest.raises(IndexFileError, match="corrupt"):
        load_index(path, 2)
    vlad_file.unlink()
    with pytest.raises(IndexFileError, match="missing"):
        load_index(path, 2)
    np.savez(  # format 1: the float VLADs inside the .npz
        path,
        ids=np.arange(40),
        codes=codes,
        vlads=vlads,
        poses=poses,
        map_version=np.array(2),
        format_version=np.array(1),
    )
    with pytest.raises(IndexFileError, match="older layout"):
        load_index(path, 2)


def test_rebuilding_from_batches_writes_the_files_without_holding_the_vlads(tmp_path):
    vlads, codes, poses, rng = _map(300, seed=5)
    batches = [
        MapVectors(
            np.arange(s, min(s + 64, 300)), vlads[s : s + 64], codes[s : s + 64], poses[s : s + 64]
        )
        for s in range(0, 300, 64)
    ]
    built = rebuild_index(tmp_path / "m.index.npz", iter(batches), 9)
    assert len(built) == 300 and built.unpersisted == 0
    np.testing.assert_array_equal(built.vlads_at(np.arange(300)), vlads)
    q = _noisy(rng, vlads[123])
    assert built.search(q, vlad_binary_code(q), k=1).entry_ids[0] == 123
    empty = rebuild_index(tmp_path / "e.index.npz", iter([]), 1)
    assert len(empty) == 0 and len(load_index(tmp_path / "e.index.npz", 1)) == 0


def test_id_lookup_follows_random_adds_and_removes():
    vlads, codes, poses, rng = _map(400, seed=6)
    index, model = RetrievalIndex(IndexConfig(scan_min_entries=150)), set()
    for _ in range(40):
        ids = rng.choice(400, 25, replace=False)
        if rng.random() < 0.6:
            index.add(ids * 7, codes[ids], vlads[ids], poses[ids])
            model |= set((ids * 7).tolist())
        else:
            assert index.remove(ids * 7) == len(model & set((ids * 7).tolist()))
            model -= set((ids * 7).tolist())
        assert sorted(index.entry_ids().tolist()) == sorted(model) and len(index) == len(model)
    for entry_id in list(model)[:40]:
        row = entry_id // 7
        assert entry_id in index and entry_id + 1 not in index
        assert index.search(vlads[row], codes[row], k=1).entry_ids[0] == entry_id


def test_the_float_file_reads_rows_in_any_order_repeated_and_in_long_runs(tmp_path):
    """VladFile.take reads file rows adjacent to each other in one call: whatever the order
    asked, rows asked twice, runs longer than one call's buffers, each row lands in its
    place."""
    rng = np.random.default_rng(7)
    vlads = rng.normal(size=(700, 2048)).astype(np.float32)
    path = tmp_path / "vlads.npy"
    np.save(path, vlads)
    with open(path, "rb") as f:
        np.lib.format.read_magic(f)
        np.lib.format.read_array_header_1_0(f)
        offset = f.tell()
    store = VladFile(path, len(vlads), offset)
    for rows in (
        rng.permutation(700)[:30],
        np.array([5, 6, 7, 7, 8, 3, 4, 699, 0]),
        np.arange(700),  # one run longer than a call's buffers
        np.arange(700)[::-1],
        np.array([], dtype=np.int64),
    ):
        out = np.empty((len(rows), 2048), dtype=np.float32)
        store.take(rows, out)
        assert np.array_equal(out, vlads[rows])
    with pytest.raises(IndexError):
        store.take(np.array([3, 700]), np.empty((2, 2048), dtype=np.float32))

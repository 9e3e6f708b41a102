import numpy as np
import pytest

from monoloc.core.prior import RetrievalPrior
from monoloc.server.index._scan_kernel import BLOCK, scan, select_nearest
from monoloc.server.index.persist import load_index, save_index
from monoloc.server.index.retrieval import IndexConfig, RetrievalIndex
from monoloc.server.index.sketch import SketchTable, sketch_projection, vlad_sketch
from monoloc.server.vision.binary_code import hamming_distances, vlad_binary_code


def _unit(rng, n, dim=2048):
    v = rng.normal(size=(n, dim)).astype(np.float32)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.mark.parametrize("size", [1, 31, 1000, 5003])
def test_scan_returns_the_nearest_sketches_in_order(size):
    rng = np.random.default_rng(size)
    # Few distinct codes with 0-3 flipped bits: many exact ties, the case that decides.
    bases = rng.integers(0, 256, size=(max(size // 20, 2), 32), dtype=np.uint8)
    sketches = bases[rng.integers(0, len(bases), size)]
    bits = np.unpackbits(sketches, axis=1)
    for row in bits:
        row[rng.integers(0, 256, rng.integers(0, 4))] ^= 1
    sketches = np.packbits(bits, axis=1)
    table = SketchTable()
    table.reserve(size + 7, 0)
    table.set_rows(0, sketches)
    query = sketches[size // 2].copy()
    query[0] ^= 0b101
    truth = hamming_distances(query, sketches)
    for n_wanted in (1, 10, size, size + 5):
        rows = table.nearest(query, size, n_wanted)
        assert len(rows) == min(n_wanted, size)
        assert len(set(rows.tolist())) == len(rows)
        got = truth[rows]
        assert np.all(np.diff(got) >= 0)
        assert np.array_equal(got, np.sort(truth)[: len(rows)])


def test_scan_kernel_ranges_compose():
    rng = np.random.default_rng(1)
    words_t = np.ascontiguousarray(
        rng.integers(0, 256, size=(3 * BLOCK + 5, 32), dtype=np.uint8).view(np.uint64).T
    )
    query = rng.integers(0, 256, size=32, dtype=np.uint8).view(np.uint64)
    n = words_t.shape[1]
    whole, split = np.empty(4, np.int32), np.empty(4, np.int32)
    bytes_whole, bytes_split = np.empty(n, np.uint8), np.empty(n, np.uint8)
    scan(query, words_t, 0, n, bytes_whole, whole)
    scan(query, words_t, 2 * BLOCK, n, bytes_split, split)
    scan(query, words_t, 0, 2 * BLOCK, bytes_split, split)
    distances = hamming_distances(
        query.view(np.uint8), np.ascontiguousarray(words_t.T).view(np.uint8)
    )
    assert np.array_equal(whole, split)
    assert np.array_equal(bytes_whole, bytes_split)
    assert np.array_equal(bytes_whole, distances)
    assert whole.tolist() == [distances[b * BLOCK : (b + 1) * BLOCK].min() for b in range(4)]
    out = np.empty(7, np.int64)
    assert select_nearest(bytes_whole, whole, n, 7, out) == 7
    assert np.array_equal(distances[out], np.sort(distances)[:7])


def test_scan_of_opposite_sketches_clamps_at_255_and_still_selects():
    """Distances of 256 are stored as 255: the selection still returns the wanted rows,
    ordered up to that clamp (the full codes order the candidates afterwards)."""
    rng = np.random.default_rng(2)
    query = rng.integers(0, 256, size=32, dtype=np.uint8)
    sketches = np.repeat(~query[None], 2 * BLOCK + 3, axis=0)  # every distance is 256
    sketches[5, 0] ^= 1  # 255
    sketches[70, :2] ^= 0xFF  # 240
    table = SketchTable()
    table.reserve(len(sketches), 0)
    table.set_rows(0, sketches)
    rows = table.nearest(query, len(sketches), 20)
    assert len(rows) == 20 and len(set(rows.tolist())) == 20
    assert rows[0] == 70
    assert rows[1] == 5 or hamming_distances(query, sketches[rows[1:2]])[0] == 256
    # Every row wanted, the last block holding only distances of 256.
    rows = table.nearest(query, len(sketches), len(sketches))
    assert sorted(rows.tolist()) == list(range(len(sketches)))


def test_sketch_distance_estimates_the_angle():
    projection = sketch_projection()
    assert projection.shape == (2048, 256)
    assert np.allclose(projection.T @ projection, np.eye(256), atol=1e-4)
    rng = np.random.default_rng(2)
    a = _unit(rng, 400)
    # Partners at known angles: 30, 60 and 90 degrees on average.
    errors = []
    for angle_deg in (30.0, 60.0, 90.0):
        other = _unit(rng, 400)
        other -= (other * a).sum(1, keepdims=True) * a
        other /= np.linalg.norm(other, axis=1, keepdims=True)
        b = np.cos(np.radians(angle_deg)) * a + np.sin(np.radians(angle_deg)) * other
        bits = np.bitwise_count(vlad_sketch(a) ^ vlad_sketch(b)).sum(1)
        errors.append(abs(bits.mean() / 256 - angle_deg / 180))
    assert max(errors) < 0.01
    assert np.array_equal(vlad_sketch(a[3]), vlad_sketch(a)[3])


def _route(rng, n):
    """Unit vectors whose neighbours along the index are alike (AR(1) prototypes)."""
    protos = np.empty((n, 2048), dtype=np.float32)
    p = rng.normal(size=2048).astype(np.float32)
    for i in range(n):
        p = 0.9 * p + np.sqrt(1 - 0.81) * rng.normal(size=2048).astype(np.float32)
        protos[i] = p
    views = protos + 0.6 * rng.normal(size=protos.shape).astype(np.float32)
    return views / np.linalg.norm(views, axis=1, keepdims=True)


def test_scan_index_live_edits_prior_and_persistence(tmp_path):
    rng = np.random.default_rng(3)
    n = 3000
    vlads = _route(rng, n)
    codes = vlad_binary_code(vlads)
    poses = np.zeros((n, 3))
    poses[:, 0] = np.arange(n) * 1.0
    config = IndexConfig(scan_min_entries=1000, scan_candidates=300, scan_shortlist=50)
    index = RetrievalIndex.from_arrays(np.arange(n), codes, vlads, poses, config)
    assert index.kind == "scan" and index._faiss is None
    exact = np.argsort(np.linalg.norm(vlads - vlads[1234], axis=1))[:10]
    assert set(index.search(vlads[1234], codes[1234], k=10).entry_ids.tolist()) == set(exact)
    # Removing rows moves the last rows into the holes: those stay findable, removed never.
    index.remove(np.arange(100, 160))
    for i in (2999, 2950, 500):
        assert index.search(vlads[i], codes[i], k=1).entry_ids[0] == i
    assert not set(index.search(vlads[130], codes[130], k=10).entry_ids.tolist()) & set(
        range(100, 160)
    )
    index.add([130], codes[130:131], vlads[130:131], poses[130:131])
    assert index.search(vlads[130], codes[130], k=1).entry_ids[0] == 130
    # A prior keeps only entries inside it, even far down the sketch ranking.
    prior = RetrievalPrior(x_m=2500.0, y_m=0.0, radius_m=5.0)
    res = index.search(vlads[10], codes[10], k=5, prior=prior)
    assert len(res.entry_ids) == 5 and np.all(np.abs(res.entry_ids - 2500) <= 5)
    # Persisted sketches are used as they are; a file without them recomputes them.
    save_index(tmp_path / "i.npz", index, 3)
    loaded = load_index(tmp_path / "i.npz", 3, config)
    assert loaded.kind == "scan" and len(loaded) == len(index)
    assert np.array_equal(loaded._sketches.rows(len(loaded)), index._sketches.rows(len(index)))
    snap = index.snapshot()
    rebuilt = RetrievalIndex.from_arrays(
        snap["ids"], snap["codes"], snap["vlads"], snap["poses"], config
    )
    assert np.array_equal(rebuilt._sketches.rows(len(rebuilt)), snap["sketches"])

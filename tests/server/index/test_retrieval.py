import threading

import numpy as np
import pytest

from monoloc.core.errors import InvalidInputError
from monoloc.core.prior import RetrievalPrior
from monoloc.server.index.persist import IndexFileError, load_index, save_index
from monoloc.server.index.retrieval import IndexConfig, RetrievalIndex


def _places(rng, n_places, views_per_place, noise=0.6):
    """Unit VLAD-like vectors along a route: neighbouring places look alike (a random walk
    of prototypes) and views of one place are noisy copies of its prototype."""
    steps = rng.normal(size=(n_places, 2048)).astype(np.float32)
    protos = np.cumsum(steps, axis=0) / 3.0 + rng.normal(size=(1, 2048)).astype(np.float32)
    protos = (protos + 2.0 * steps).astype(np.float32)
    vlads = np.repeat(protos, views_per_place, axis=0)
    vlads += noise * rng.normal(size=vlads.shape).astype(np.float32)
    vlads /= np.linalg.norm(vlads, axis=1, keepdims=True)
    poses = np.zeros((len(vlads), 3))
    poses[:, 0] = np.repeat(np.arange(n_places) * 5.0, views_per_place)
    return vlads, poses


def _codes(vlads):
    return np.packbits(vlads > 0, axis=-1)


def _exact_topk(vlads, q, k):
    d = np.linalg.norm(vlads - q, axis=1)
    return np.argsort(d)[:k]


def test_search_matches_exact_float_ranking():
    rng = np.random.default_rng(0)
    vlads, poses = _places(rng, 300, 3)
    ids = np.arange(len(vlads)) + 1000
    index = RetrievalIndex.from_arrays(ids, _codes(vlads), vlads, poses)
    recalls = []
    for i in rng.choice(len(vlads), 50, replace=False):
        q = vlads[i] + 0.4 * rng.normal(size=2048).astype(np.float32) / np.sqrt(2048)
        q /= np.linalg.norm(q)
        res = index.search(q, _codes(q), k=10)
        truth = set(ids[_exact_topk(vlads, q, 10)])
        recalls.append(len(truth & set(res.entry_ids.tolist())) / 10)
        assert np.all(np.diff(res.distances) >= 0)
    assert np.mean(recalls) >= 0.95


def test_prior_restricts_candidates_and_heading_window():
    rng = np.random.default_rng(1)
    vlads, poses = _places(rng, 50, 2)
    poses[1::2, 2] = np.pi  # every other view looks the other way
    ids = np.arange(len(vlads))
    index = RetrievalIndex.from_arrays(ids, _codes(vlads), vlads, poses)
    q = vlads[0]
    prior = RetrievalPrior(x_m=100.0, y_m=0.0, radius_m=12.0)
    res = index.search(q, _codes(q), k=10, prior=prior)
    assert set(res.entry_ids.tolist()) <= {i for i in ids if abs(poses[i, 0] - 100) <= 12}
    assert len(res.entry_ids) == 10
    facing = RetrievalPrior(100.0, 0.0, 12.0, yaw_rad=3.1, yaw_tolerance_rad=0.2)
    res = index.search(q, _codes(q), k=10, prior=facing)
    assert len(res.entry_ids) == 5 and np.all(poses[res.entry_ids, 2] == np.pi)
    with pytest.raises(InvalidInputError):
        RetrievalPrior(0.0, 0.0, -1.0)


def test_add_replace_and_remove_live():
    rng = np.random.default_rng(2)
    vlads, poses = _places(rng, 20, 1, noise=0.0)
    index = RetrievalIndex.from_arrays(np.arange(10), _codes(vlads[:10]), vlads[:10], poses[:10])
    index.add(np.arange(10, 20), _codes(vlads[10:]), vlads[10:], poses[10:])
    assert len(index) == 20
    res = index.search(vlads[15], _codes(vlads[15]), k=1)
    assert res.entry_ids[0] == 15 and res.distances[0] < 1e-5
    assert index.remove([15, 3, 999]) == 2
    res = index.search(vlads[15], _codes(vlads[15]), k=3)
    assert 15 not in res.entry_ids and len(index) == 18
    # The entry that moved into a hole is still found.
    res = index.search(vlads[19], _codes(vlads[19]), k=1)
    assert res.entry_ids[0] == 19
    # Re-adding an existing id replaces it.
    index.add([19], _codes(vlads[:1]), vlads[:1], poses[:1])
    assert len(index) == 18
    assert index.search(vlads[0], _codes(vlads[0]), k=2).entry_ids.tolist() in ([0, 19], [19, 0])


def test_concurrent_add_remove_while_searching():
    rng = np.random.default_rng(3)
    vlads, poses = _places(rng, 400, 1, noise=0.0)
    codes = _codes(vlads)
    index = RetrievalIndex.from_arrays(np.arange(200), codes[:200], vlads[:200], poses[:200])
    errors: list[BaseException] = []
    stop = threading.Event()

    def searcher():
        try:
            while not stop.is_set():
                for i in range(0, 200, 17):
                    res = index.search(vlads[i], codes[i], k=1)
                    assert res.entry_ids[0] == i  # the first 200 are never removed
        except BaseException as exc:  # noqa: BLE001 - surfaced below
            errors.append(exc)

    threads = [threading.Thread(target=searcher) for _ in range(3)]
    for t in threads:
        t.start()
    for i in range(200, 400, 10):
        index.add(np.arange(i, i + 10), codes[i : i + 10], vlads[i : i + 10], poses[i : i + 10])
        index.remove(np.arange(i, i + 5))
    stop.set()
    for t in threads:
        t.join()
    assert not errors, errors[0]
    assert len(index) == 300
    assert index.search(vlads[399], codes[399], k=1).entry_ids[0] == 399


def test_large_map_index_keeps_recall():
    rng = np.random.default_rng(4)
    vlads, poses = _places(rng, 1500, 2)
    config = IndexConfig(scan_min_entries=2000)
    index = RetrievalIndex.from_arrays(np.arange(3000), _codes(vlads), vlads, poses, config)
    assert index.kind == "scan"
    rows = range(0, 3000, 60)
    hits = [index.search(vlads[i], _codes(vlads[i]), k=1).entry_ids[0] == i for i in rows]
    assert np.mean(hits) >= 0.95


def test_k_above_the_scan_shortlist_still_returns_k():
    rng = np.random.default_rng(7)
    vlads, poses = _places(rng, 300, 2)
    config = IndexConfig(scan_min_entries=500, scan_shortlist=5, scan_candidates=200)
    index = RetrievalIndex.from_arrays(np.arange(600), _codes(vlads), vlads, poses, config)
    assert index.kind == "scan"
    found = index.search(vlads[100], _codes(vlads[100]), k=20)
    assert len(found.entry_ids) == 20
    assert found.entry_ids[0] == 100
    assert np.all(np.diff(found.distances) >= 0)
    exact = np.linalg.norm(vlads[found.entry_ids] - vlads[100], axis=1)
    np.testing.assert_allclose(found.distances, exact, atol=1e-5)


def test_persist_round_trip_stale_and_corrupt(tmp_path):
    rng = np.random.default_rng(5)
    vlads, poses = _places(rng, 30, 1)
    index = RetrievalIndex.from_arrays(np.arange(30), _codes(vlads), vlads, poses)
    path = tmp_path / "map_1.index.npz"
    save_index(path, index, map_version=7)
    loaded = load_index(path, expected_map_version=7)
    assert len(loaded) == 30
    assert loaded.search(vlads[4], _codes(vlads[4]), k=1).entry_ids[0] == 4
    with pytest.raises(IndexFileError, match="stale"):
        load_index(path, expected_map_version=8)
    with pytest.raises(IndexFileError, match="missing"):
        load_index(tmp_path / "nope.npz", expected_map_version=7)
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    path.write_bytes(bytes(raw))
    with pytest.raises(IndexFileError):
        load_index(path, expected_map_version=7)
    assert not list(tmp_path.glob("*.tmp"))


def test_a_map_grows_from_the_flat_index_into_the_scan_and_persists(tmp_path):
    rng = np.random.default_rng(6)
    vlads, poses = _places(rng, 600, 1)
    codes = _codes(vlads)
    config = IndexConfig(scan_min_entries=500)
    first = slice(0, 400)
    index = RetrievalIndex.from_arrays(
        np.arange(400), codes[first], vlads[first], poses[first], config
    )
    assert index.kind == "flat"
    index.add(np.arange(400, 600), codes[400:], vlads[400:], poses[400:])
    assert index.kind == "scan" and index.search(vlads[450], codes[450], k=1).entry_ids[0] == 450
    index.remove(np.arange(0, 200))  # shrinking under the size keeps the scan
    index.add([0], codes[:1], vlads[:1], poses[:1])
    assert index.kind == "scan" and len(index) == 401
    assert index.search(vlads[0], codes[0], k=1).entry_ids[0] == 0
    save_index(tmp_path / "i.npz", index, 1)
    loaded = load_index(tmp_path / "i.npz", 1, IndexConfig(scan_min_entries=400))
    assert loaded.kind == "scan" and len(loaded) == 401
    assert loaded.search(vlads[377], codes[377], k=1).entry_ids[0] == 377

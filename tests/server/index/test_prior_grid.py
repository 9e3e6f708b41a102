"""The planar grid that finds a prior's rows: the same rows as the brute-force mask over
every pose, through random adds, replacements, removals and a save and load."""

import numpy as np

from monoloc.core.prior import RetrievalPrior
from monoloc.server.index.grid import MAX_GRID_ROWS, PlanarGrid
from monoloc.server.index.persist import load_index, save_index
from monoloc.server.index.retrieval import IndexConfig, RetrievalIndex


def _layout(rng, n, cell_m=16.0):
    """Planar poses (n, 3): a scatter over 1 km, dense clusters (a car park), points on
    cell edges and corners, and a few duplicates."""
    poses = np.empty((n, 3))
    poses[:, 0] = rng.uniform(-500, 500, n)
    poses[:, 1] = rng.uniform(-500, 500, n)
    poses[:, 2] = rng.uniform(-np.pi, np.pi, n)
    cluster = rng.random(n) < 0.3
    poses[cluster, :2] = rng.normal(size=(cluster.sum(), 2)) * 6.0 + [40.0, -25.0]
    edges = rng.random(n) < 0.15
    poses[edges, :2] = rng.integers(-30, 30, size=(edges.sum(), 2)) * cell_m
    half = rng.random(n) < 0.1
    poses[half, 0] = rng.integers(-30, 30, size=half.sum()) * cell_m
    poses[-5:] = poses[:5]
    return poses


def _random_prior(rng, poses):
    """A prior around a random pose or a random point, its radius 0.5-200 m; a third
    of them with a heading window; some with their circle through a pose exactly."""
    x, y = poses[rng.integers(len(poses)), :2] if rng.random() < 0.7 else rng.uniform(-600, 600, 2)
    radius = float(np.exp(rng.uniform(np.log(0.5), np.log(200.0))))
    if rng.random() < 0.2:  # the circle through another pose, or a cell edge away
        other = poses[rng.integers(len(poses)), :2]
        radius = max(float(np.hypot(other[0] - x, other[1] - y)), 0.1)
    if rng.random() < 0.33:
        return RetrievalPrior(float(x), float(y), radius, float(rng.uniform(-4, 4)), 0.7)
    return RetrievalPrior(float(x), float(y), radius)


def _assert_same_as_mask(index, rng, n_priors=40):
    poses = index.poses_world()
    through_grid = 0
    for _ in range(n_priors):
        prior = _random_prior(rng, poses)
        expected = np.flatnonzero(prior.mask(poses))
        got = index._inside_rows(prior)
        np.testing.assert_array_equal(got, expected)
        through_grid += index._grid.candidates(prior, max_rows=len(index) // 2) is not None
    assert through_grid >= n_priors // 2  # most priors are small: the grid answered them
    assert len(index._grid) == len(index)


def _vectors(rng, n):
    vlads = rng.normal(size=(n, 2048)).astype(np.float32)
    vlads /= np.linalg.norm(vlads, axis=1, keepdims=True)
    return vlads, np.packbits(vlads > 0, axis=-1)


def test_the_grid_gives_the_masks_rows_through_random_adds_and_removes():
    rng = np.random.default_rng(11)
    n = 2000
    poses = _layout(rng, n)
    vlads, codes = _vectors(rng, n)
    index = RetrievalIndex.from_arrays(np.arange(n), codes, vlads, poses)
    _assert_same_as_mask(index, rng)
    next_id = n
    for step in range(12):
        if step % 3 == 0:  # new entries, some replacing present ones (new poses)
            m = int(rng.integers(1, 300))
            new_ids = np.arange(next_id, next_id + m)
            next_id += m
            replaced = rng.choice(index.entry_ids(), int(rng.integers(0, 40)), replace=False)
            ids = np.concatenate([new_ids, replaced])
            v, c = _vectors(rng, len(ids))
            index.add(ids, c, v, _layout(rng, len(ids)))
        else:  # removals: random ones, a run of the last rows, ids not present
            present = index.entry_ids()
            gone = rng.choice(present, int(rng.integers(1, 200)), replace=False)
            gone = np.concatenate([gone, present[-int(rng.integers(1, 20)) :], [10**9]])
            index.remove(gone)
        _assert_same_as_mask(index, rng, n_priors=25)


def test_the_grid_survives_a_save_and_a_load(tmp_path):
    rng = np.random.default_rng(12)
    n = 1500
    poses = _layout(rng, n)
    vlads, codes = _vectors(rng, n)
    index = RetrievalIndex.from_arrays(np.arange(n), codes, vlads, poses)
    index.remove(rng.choice(n, 300, replace=False))
    v, c = _vectors(rng, 100)
    index.add(np.arange(n, n + 100), c, v, _layout(rng, 100))
    save_index(tmp_path / "map_1.index.npz", index, 3)
    loaded = load_index(tmp_path / "map_1.index.npz", 3)
    np.testing.assert_array_equal(loaded.entry_ids(), index.entry_ids())
    _assert_same_as_mask(loaded, rng)
    loaded.remove(loaded.entry_ids()[::7])
    _assert_same_as_mask(loaded, rng)
    # A search with a prior returns entries inside it only, nearest first.
    prior = RetrievalPrior(40.0, -25.0, 10.0)
    poses_now, ids_now = loaded.poses_world(), loaded.entry_ids()
    inside_ids = set(ids_now[prior.mask(poses_now)].tolist())
    row = int(np.flatnonzero(prior.mask(poses_now))[0])
    query = loaded.vlads_at(np.array([row]))[0]
    found = loaded.search(query, np.packbits(query > 0), k=10, prior=prior)
    assert found.entry_ids[0] == ids_now[row]
    assert set(found.entry_ids.tolist()) <= inside_ids
    assert len(found.entry_ids) == min(10, len(inside_ids))


def test_edges_circles_and_non_finite_poses():
    cell = 16.0
    grid = PlanarGrid(cell)
    r = 16.0
    on_circle = [(r, 0.0), (-r, 0.0), (0.0, r), (0.0, -r), (r / np.sqrt(2), -r / np.sqrt(2))]
    on_edges = [(x, y) for x in (-32.0, -16.0, 0.0, 16.0, 32.0) for y in (-16.0, 0.0, 16.0)]
    just_out = [(r + 1e-9, 0.0), (0.0, -r - 1e-9), (np.nextafter(-r, -np.inf), 0.0)]
    xy = np.array(on_circle + on_edges + just_out + [(np.nan, 0.0), (np.inf, 1.0), (5.0, -np.inf)])
    poses = np.c_[xy, np.zeros(len(xy))]
    grid.build(poses)
    for cx, cy in [(0.0, 0.0), (16.0, 0.0), (-16.0, 16.0), (1e-12, -1e-12)]:
        prior = RetrievalPrior(cx, cy, r)
        inside = np.flatnonzero(prior.mask(poses))
        found = grid.candidates(prior)
        assert len(np.unique(found)) == len(found)
        assert set(inside.tolist()) <= set(found.tolist())
    assert set(np.flatnonzero(RetrievalPrior(0.0, 0.0, r).mask(poses)).tolist()) >= set(range(5))
    # Rounding: the mask finds this pose inside, though it lies past the disk's edge
    # x = -32 (a cell edge) by an ulp; the grid's padding keeps its cell.
    prior = RetrievalPrior(86.80870319124995, 0.0, 118.80870319124995)
    pose = np.array([[np.nextafter(-32.0, -np.inf), 0.0, 0.0]])
    assert prior.mask(pose)[0]
    grid.build(np.r_[poses, pose])
    assert len(poses) in set(grid.candidates(prior).tolist())
    # Far from everything, nothing; a disk over more grid rows than the limit, None.
    assert len(grid.candidates(RetrievalPrior(5000.0, 5000.0, 10.0))) == 0
    assert grid.candidates(RetrievalPrior(0.0, 0.0, cell * MAX_GRID_ROWS)) is None


def test_a_small_prior_reads_its_cells_only():
    poses = np.c_[np.arange(100_000) * 0.5, np.zeros(100_000), np.zeros(100_000)]
    grid = PlanarGrid(16.0)
    grid.build(poses)
    prior = RetrievalPrior(20_000.3, 0.0, 50.0)
    found = grid.candidates(prior)
    # the cells from x = 19,936 to 20,064 m hold 8 x 32 rows
    assert 200 < len(found) <= 8 * 32
    assert set(np.flatnonzero(prior.mask(poses)).tolist()) <= set(found.tolist())
    assert grid.nbytes == 16 * len(poses)
    index = RetrievalIndex(IndexConfig(prior_cell_m=4.0))
    assert index._grid.cell_m == 4.0

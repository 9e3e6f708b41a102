"""Coverage gaps along a route: a straight street with a hole in its entries."""

from __future__ import annotations

import numpy as np
import pytest

from monoloc.server.api.console.coverage import (
    CoverageConfig,
    route_gaps,
    route_length_m,
    sample_route,
)


def test_samples_keep_the_vertices_and_the_step():
    route = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 5.0]])
    points, arcs = sample_route(route, 1.0)
    assert len(points) == 16 and arcs[-1] == pytest.approx(15.0)
    assert np.all(np.diff(arcs) <= 1.0 + 1e-9)
    for vertex in route:
        assert np.min(np.linalg.norm(points - vertex, axis=1)) == 0.0


def test_a_hole_in_the_entries_is_one_gap_of_its_length():
    route = np.stack([np.arange(0.0, 101.0, 2.0), np.zeros(51)], axis=1)
    covered = route[(route[:, 0] < 40) | (route[:, 0] > 60)]  # nothing from 40 to 60 m
    config = CoverageConfig(radius_m=5.0, step_m=0.25)
    (gap,) = route_gaps(route, covered, config, run_id=3)
    assert gap.run_id == 3
    # uncovered: farther than 5 m from the last entry before (38) and the first after (62)
    assert gap.points_xy_m[0, 0] == pytest.approx(43.25)
    assert gap.points_xy_m[-1, 0] == pytest.approx(56.75)
    assert gap.length_m == pytest.approx(13.5)
    assert route_gaps(route, route, config) == []


def test_no_selected_entry_leaves_the_whole_route_uncovered():
    route = np.array([[0.0, 0.0], [3.0, 4.0]])
    (gap,) = route_gaps(route, np.zeros((0, 2)))
    assert gap.length_m == pytest.approx(route_length_m(route)) == pytest.approx(5.0)


def test_bad_radius_is_refused():
    with pytest.raises(ValueError, match="radius_m must be"):
        route_gaps(np.zeros((2, 2)), np.zeros((1, 2)), CoverageConfig(radius_m=0.0))


def test_sample_count_is_what_sampling_returns():
    from monoloc.server.api.console.coverage import sample_count, sample_route

    route = np.array([[0.0, 0.0], [3.0, 4.0], [3.0, 4.0], [10.0, 4.0]])
    for step_m in (0.025, 0.3, 1.0, 50.0):
        assert sample_count(route, step_m) == len(sample_route(route, step_m)[0])


def test_thin_gaps_keeps_ends_lengths_and_the_limit():
    from monoloc.server.api.console.coverage import Gap, thin_gaps

    gaps = [Gap(1, np.c_[np.arange(n), np.zeros(n)].astype(float), float(n)) for n in (50, 7, 300)]
    thinned, left_out = thin_gaps(gaps, max_points=40)
    assert left_out and sum(len(g.points_xy_m) for g in thinned) <= 40
    for before, after in zip(gaps, thinned, strict=True):
        assert after.length_m == before.length_m
        assert (after.points_xy_m[[0, -1]] == before.points_xy_m[[0, -1]]).all()
    many = [Gap(1, np.zeros((3, 2)), float(i)) for i in range(100)]
    kept, _ = thin_gaps(many, max_points=10)
    assert sum(len(g.points_xy_m) for g in kept) <= 10 and kept[0].length_m == 99.0
    assert thin_gaps(gaps, max_points=10_000) == (gaps, False)

"""How a calibration fits the map it is applied to (``calibrate.calibration_fit``): the
VLAD distances between a map's entries 2-6 m apart against the training run's."""

from __future__ import annotations

import numpy as np
import pytest

from monoloc.server.calibrate import calibration_fit, neighbour_vlad_distances, vlad_statistics


def _street(n: int, spacing_m: float, roughness: float, seed: int):
    """Entries along a line ``spacing_m`` apart, unit VLADs drifting by ``roughness``
    per metre (a street whose look changes faster has larger distances)."""
    rng = np.random.default_rng(seed)
    poses = np.c_[np.arange(n) * spacing_m, np.zeros(n), np.zeros(n)]
    steps = rng.normal(0.0, roughness * np.sqrt(spacing_m), (n, 64))
    vlads = 1.0 + np.cumsum(steps, axis=0)
    return poses, vlads / np.linalg.norm(vlads, axis=1, keepdims=True)


def _distances(n: int, spacing_m: float, roughness: float, seed: int) -> np.ndarray:
    poses, vlads = _street(n, spacing_m, roughness, seed)
    return neighbour_vlad_distances(poses, lambda rows: vlads[rows])


def test_neighbour_distances_take_only_entries_in_the_band():
    poses, vlads = _street(40, 1.0, 0.05, 0)
    seen = []

    def vlads_at(rows):
        seen.append(np.asarray(rows))
        return vlads[rows]

    d = neighbour_vlad_distances(poses, vlads_at)
    # each entry has the others 2..6 m away on either side: 10 pairs inside the street
    assert 10 * 28 <= len(d) <= 10 * 40 and np.all(d > 0)
    expected = [
        np.linalg.norm(vlads[i] - vlads[j])
        for i in range(40)
        for j in range(40)
        if 2.0 <= abs(i - j) <= 6.0
    ]
    np.testing.assert_allclose(np.sort(d), np.sort(expected))
    assert len(neighbour_vlad_distances(poses[:1], vlads_at)) == 0
    # a large map is sampled: at most max_entries entries start a pair
    big = neighbour_vlad_distances(
        *_street(500, 1.0, 0.05, 1)[:1], lambda r: vlads[r % 40], max_entries=50
    )
    assert 0 < len(big) <= 50 * 10


def test_a_map_whose_streets_look_like_the_training_run_fits_another_warns():
    train = _distances(60, 2.0, 0.05, 2)
    provenance = {"vlad_neighbours": vlad_statistics(train)}
    alike = _distances(200, 1.0, 0.05, 3)
    other = _distances(200, 1.0, 0.12, 4)
    fit = calibration_fit(provenance, alike)
    assert fit["fits"] is True and fit["warning"] is None
    assert abs(fit["shift_in_training_std"]) <= 1.0  # the spacing does not matter
    fit = calibration_fit(provenance, other)
    assert fit["fits"] is False and fit["shift_in_training_std"] > 1.0
    assert "calibrate on a run that looks like this map" in fit["warning"]
    # a calibration stored before the check: not known
    assert calibration_fit({}, alike)["fits"] is None


@pytest.mark.parametrize("n", [0, 1])
def test_statistics_of_too_few_distances_are_none(n):
    stats = vlad_statistics(np.ones(n))
    assert stats["n"] == n and stats["std"] is None

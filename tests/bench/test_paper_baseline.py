"""The paper-faithful baseline (bench.lab.paper) runs behind the localization stage's
interfaces: exact float k-NN over all VLADs, OpenCV brute-force matching per entry,
independent RANSAC per entry. On the same frames and seed it retrieves what the
product's shortlist retrieves and its hypotheses are as close to the truth as the
product's guided ones."""

from __future__ import annotations

import numpy as np
import pytest
from sim_city import ingested_city

from monoloc.core.geometry import planar_from_T_world_from_cam

N_FRAMES = 5


@pytest.fixture(scope="module")
def city(tmp_path_factory):
    return ingested_city(tmp_path_factory.mktemp("paper_city"), seed=5, frames=40)


def _per_entry(result) -> dict[int, np.ndarray]:
    return {h.entry_id: h.pose_world for h in result.hypotheses if not h.joint}


# Ingests its own 40-frame city (~50 s on 2 cores): a lab baseline's check, run by `make bench`.
@pytest.mark.slow
def test_the_paper_baseline_retrieves_the_same_entries_and_is_no_closer_to_the_truth(
    city, monkeypatch
):
    import monoloc.server.vision.matching as matching
    from bench.lab.paper import PAPER_STAGES
    from monoloc.server.localize import LocalizeConfig

    registry, query_run = city
    calls = []
    bruteforce = matching.match_descriptors_bruteforce

    def counted(*args, **kwargs):
        calls.append(1)
        return bruteforce(*args, **kwargs)

    monkeypatch.setattr(matching, "match_descriptors_bruteforce", counted)
    config = LocalizeConfig()
    both, only_one = [], 0
    errors = {"product": [], "paper": []}
    frames = query_run.frames[1 :: max(1, len(query_run.frames) // N_FRAMES)][:N_FRAMES]
    assert len(frames) == N_FRAMES
    for frame in frames:
        image = query_run.load(frame).image_gray
        truth = planar_from_T_world_from_cam(frame.T_world_from_cam)
        product, _ = registry.localize(1, image, config, np.random.default_rng(11))
        assert calls == []  # the product never brute-forces
        paper, _ = registry.localize(
            1, image, config, np.random.default_rng(11), stages=PAPER_STAGES
        )
        assert len(calls) == len(paper.retrieved_ids)  # one matcher per entry
        calls.clear()
        # exact k-NN == the shortlist's re-ranked top-k
        assert paper.retrieved_ids.tolist() == product.retrieved_ids.tolist()
        np.testing.assert_allclose(paper.retrieved_distances, product.retrieved_distances, 1e-5)
        assert paper.joint is None and all(h.method == "ransac" for h in paper.hypotheses)
        assert all(h.covariance_px1 is None for h in paper.hypotheses)
        ours, theirs = _per_entry(product), _per_entry(paper)
        only_one += len(ours.keys() ^ theirs.keys())
        for entry_id in ours.keys() & theirs.keys():
            both.append(ours[entry_id] - theirs[entry_id])
            errors["product"].append(np.hypot(*(ours[entry_id][:2] - truth[:2])))
            errors["paper"].append(np.hypot(*(theirs[entry_id][:2] - truth[:2])))
    both = np.array(both)
    apart_m = np.hypot(both[:, 0], both[:, 1])
    median = {name: float(np.median(e)) for name, e in errors.items()}
    assert len(both) >= 2 * N_FRAMES and only_one <= 0.25 * len(both)
    assert np.median(apart_m) < 0.03 and np.max(np.abs(both[:, 2])) < 0.01
    assert median["product"] <= 1.2 * median["paper"] + 0.005, median

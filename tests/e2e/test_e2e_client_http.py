"""MonolocClient against a live server: localize over HTTP (hypotheses parsed into
client.measurement.Hypotheses, prior and k honoured, a seed repeats an answer, the
stream gives the same answer), maps found by name, the uncalibrated map's default
measurement model, and 4xx answers raised at once with the server's message."""

from __future__ import annotations

import time
import warnings

import numpy as np
import pytest
from e2e_helpers import QUERY_SEQ

from monoloc.client.api import MonolocClient, ServerError
from monoloc.client.replay import read_run
from monoloc.core.errors import NotFoundError
from monoloc.core.measurement import Hypotheses, MeasurementModel
from monoloc.core.prior import RetrievalPrior

FRAME = 12


@pytest.fixture(scope="module")
def query(live_map):
    run = read_run(live_map.dataset, QUERY_SEQ)
    return run.image_paths[FRAME].read_bytes(), run.truth_world[FRAME]


@pytest.fixture
def client(live_map):
    with MonolocClient(live_map.url, live_map.keys.localize, timeout_s=30.0) as c:
        yield c


def test_localize_over_http_gives_hypotheses_near_the_truth(client, live_map, query):
    image, truth = query
    answer = client.localize(live_map.map_id, image, seed=3)
    hyps = answer.hypotheses
    assert isinstance(hyps, Hypotheses) and len(hyps) >= 1
    assert hyps.pose_world.shape == (len(hyps), 3) and hyps.entry_pose_world.shape[1] == 3
    assert np.all(np.isfinite(hyps.e_vlad)) and np.all(hyps.e_vlad > 0)
    best = np.argmax([h["n_inliers"] for h in answer.raw["hypotheses"]])
    assert np.hypot(*(hyps.pose_world[best, :2] - truth[:2])) < 0.5
    assert abs(hyps.pose_world[best, 2] - truth[2]) < np.radians(2)
    # the retrieved entry lies near the query (map and query drive the same street)
    assert np.hypot(*(hyps.entry_pose_world[best, :2] - truth[:2])) < 5.0
    assert answer.map_version >= 1 and answer.timings_ms["total"] > 0
    again = client.localize(live_map.map_id, image, seed=3)
    np.testing.assert_array_equal(again.hypotheses.pose_world, hyps.pose_world)


def test_prior_and_k_reach_the_server(client, live_map, query):
    image, truth = query
    near = RetrievalPrior(float(truth[0]), float(truth[1]), 6.0, float(truth[2]), 0.3)
    answer = client.localize(live_map.map_id, image, prior=near, k=3)
    wider = client.localize(live_map.map_id, image, prior=near, k=10)
    # The disc holds more than three entries, so k=3 must have cut the list to three.
    assert len(wider.raw["retrieved"]) > 3
    assert len(answer.raw["retrieved"]) == 3 and len(answer.hypotheses) >= 1
    assert [r["entry_id"] for r in answer.raw["retrieved"]] == [
        r["entry_id"] for r in wider.raw["retrieved"][:3]
    ]
    entries = answer.hypotheses.entry_pose_world
    assert np.all(np.hypot(entries[:, 0] - truth[0], entries[:, 1] - truth[1]) <= 6.0)
    far = RetrievalPrior(float(truth[0]) + 500.0, float(truth[1]), 5.0)
    nothing = client.localize(live_map.map_id, image, prior=far)
    assert nothing.raw["retrieved"] == [] and len(nothing.hypotheses) == 0
    assert nothing.hypotheses.pose_world.shape == (0, 3)


def test_the_stream_answers_like_http_without_deprecation_warnings(client, live_map, query):
    image, _ = query
    by_http = client.localize(live_map.map_id, image, seed=5, k=4)
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        with client.stream(live_map.map_id) as stream:
            stream.send(7, 0.7, image, k=4, seed=5)
            answer = stream.receive()
    assert answer["seq"] == 7 and answer["t"] == pytest.approx(0.7)
    assert answer["hypotheses"] == by_http.raw["hypotheses"]


def test_maps_are_found_by_name_or_id(client, live_map):
    assert client.find_map_id(live_map.map_name) == live_map.map_id
    assert client.find_map_id(str(live_map.map_id)) == live_map.map_id
    assert client.find_map_id(live_map.map_id) == live_map.map_id
    with pytest.raises(NotFoundError, match="no map named 'atlantis'"):
        client.find_map_id("atlantis")


def test_an_uncalibrated_map_gives_the_documented_defaults(client, live_map):
    model, calibrated = client.measurement_model(live_map.map_id)
    defaults = MeasurementModel()
    assert calibrated is False
    for name in ("mu1", "Sigma1", "mu2", "Sigma2"):
        np.testing.assert_allclose(getattr(model, name), getattr(defaults, name))
    assert model.outlier_log_density == defaults.outlier_log_density


def test_client_errors_are_raised_at_once_with_the_server_message(live_map, query):
    image, _ = query
    slow = dict(retries=3, backoff_s=60.0)  # a retry would take >= 60 s
    start = time.perf_counter()
    with MonolocClient(live_map.url, "mlk_" + "x" * 43, **slow) as stranger:
        with pytest.raises(ServerError, match="401 unknown or revoked API key") as info:
            stranger.find_map_id("city")
    assert info.value.status_code == 401
    with MonolocClient(live_map.url, live_map.keys.write, **slow) as operator:
        with pytest.raises(ServerError, match="403 .*lacks the 'localize' scope"):
            operator.localize(live_map.map_id, image)
    with MonolocClient(live_map.url, live_map.keys.localize, **slow) as car:
        with pytest.raises(NotFoundError, match="404 "):
            car.localize(live_map.map_id + 100, image)
        with pytest.raises(ServerError, match="415 ") as info:
            car.localize(live_map.map_id, b"GIF89a not a frame")
        with pytest.raises(ServerError, match="422 .*k must be") as info:
            car.request("POST", f"/v1/maps/{live_map.map_id}/localize", data={"k": "1000"},
                        files={"image": ("f.png", image, "image/png")})  # fmt: skip
    assert info.value.status_code == 422
    with MonolocClient(live_map.url, live_map.keys.localize, **slow) as car:
        with pytest.raises(ServerError, match="cannot open the stream") as info:
            car.stream(live_map.map_id + 100)
    assert info.value.status_code == 404
    with MonolocClient(live_map.url, "mlk_" + "x" * 43, **slow) as stranger:
        with pytest.raises(ServerError) as info:
            stranger.stream(live_map.map_id)
    assert info.value.status_code == 401
    assert time.perf_counter() - start < 30.0  # no retry, even on a loaded machine

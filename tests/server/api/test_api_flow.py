"""The full flow against the real app and a real SQLite file: create a map, upload a
sim run (tar), the ingestion job completes, a query frame localizes within 0.3 m; the
map survives a restart; the job's upload is cleaned up."""

from __future__ import annotations

import numpy as np
from api_helpers import (
    MAP_FRAMES,
    frame_png,
    ground_truth,
    make_settings,
    open_client,
)

from monoloc.core.geometry import planar_from_T_world_from_cam, wrap_angle

QUERY_FRAME = 8


def _localize(client, map_id, keys, image, **fields):
    return client.post(
        f"/v1/maps/{map_id}/localize",
        files={"image": ("q.png", image, "image/png")},
        data={k: str(v) for k, v in fields.items()},
        headers=keys.header("localize"),
    )


def test_upload_ingests_every_frame_and_cleans_up(ingested):
    result = ingested.job["result"]
    assert ingested.job["progress"] == 1.0
    assert result["frames_total"] == MAP_FRAMES
    assert result["entries_added"] + result["frames_skipped"] == MAP_FRAMES
    assert result["entries_added"] >= MAP_FRAMES - 2
    uploads = ingested.data_dir / "uploads"
    assert not any(uploads.iterdir()), "a finished job's upload must be deleted"


def test_query_frame_localizes_within_30cm(sim_dataset, map_copy, client_on_copy):
    r = _localize(
        client_on_copy,
        map_copy.map_id,
        map_copy.keys,
        frame_png(sim_dataset, "01", QUERY_FRAME),
        seed=7,
    )
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["hypotheses"], body
    best = body["hypotheses"][0]
    truth = planar_from_T_world_from_cam(ground_truth(sim_dataset, "01", QUERY_FRAME))
    error_m = np.hypot(best["pose"]["x_m"] - truth[0], best["pose"]["y_m"] - truth[1])
    assert error_m < 0.3, (error_m, best, truth)
    assert abs(wrap_angle(best["pose"]["yaw_rad"] - truth[2])) < np.radians(2.0)
    assert len(best["T_world_from_cam"]) == 16
    assert body["map_version"] > 0 and body["seed"] == 7
    assert set(body["timings_ms"]) >= {"decode", "features", "vlad", "retrieval", "pnp", "total"}
    assert [h["n_inliers"] for h in body["hypotheses"]] == sorted(
        (h["n_inliers"] for h in body["hypotheses"]), reverse=True
    )
    assert len(body["retrieved"]) <= 10 and body["rejected"] == len(body["rejected_entries"])


def test_prior_far_away_retrieves_nothing_query_params_work(sim_dataset, map_copy, client_on_copy):
    """The optional fields may come as query parameters too."""
    r = client_on_copy.post(
        f"/v1/maps/{map_copy.map_id}/localize",
        params={"prior_x_m": 5000.0, "prior_y_m": 5000.0, "prior_radius_m": 10.0, "k": 5},
        files={"image": ("q.png", frame_png(sim_dataset, "01", QUERY_FRAME), "image/png")},
        headers=map_copy.keys.header("localize"),
    )
    assert r.status_code == 200, r.text
    assert r.json()["retrieved"] == [] and r.json()["hypotheses"] == []
    r = client_on_copy.post(
        f"/v1/maps/{map_copy.map_id}/localize",
        params={"k": 0},
        files={"image": ("q.png", frame_png(sim_dataset, "01", QUERY_FRAME), "image/png")},
        headers=map_copy.keys.header("localize"),
    )
    assert r.status_code == 422 and "k must be" in r.json()["error"]["message"]


def test_same_seed_same_answer_and_map_survives_restart(sim_dataset, map_copy):
    image = frame_png(sim_dataset, "01", QUERY_FRAME)
    settings = make_settings(map_copy.data_dir)
    answers, maps = [], []
    for _ in range(2):  # two processes' worth of apps on one data directory
        with open_client(settings) as client:
            assert client.get("/readyz").json()["maps_loaded"] == 1
            maps.append(
                client.get(
                    f"/v1/maps/{map_copy.map_id}", headers=map_copy.keys.header("admin")
                ).json()
            )
            answers.append(_localize(client, map_copy.map_id, map_copy.keys, image, seed=11).json())
    assert maps[0] == maps[1]
    assert maps[0]["n_entries"] == map_copy.job["result"]["entries_added"]
    assert maps[0]["index_loaded"] and maps[0]["indexed_entries"] == maps[0]["n_entries"]
    for answer in answers:
        answer.pop("timings_ms")
    assert answers[0] == answers[1]


def _samples(text: str) -> dict[tuple[str, frozenset], float]:
    """The exposition parsed by prometheus_client: (name, labels) -> value."""
    from prometheus_client.parser import text_string_to_metric_families

    return {
        (s.name, frozenset(s.labels.items())): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def _sample(samples, name: str, **labels: str) -> float:
    return samples.get((name, frozenset(labels.items())), 0.0)


def test_metrics_report_routes_stages_entries_jobs_and_frames(
    sim_dataset, map_copy, client_on_copy
):
    admin = map_copy.keys.header("admin")
    _localize(client_on_copy, map_copy.map_id, map_copy.keys, frame_png(sim_dataset, "01", 3))
    samples = _samples(client_on_copy.get("/metrics", headers=admin).text)
    n = map_copy.job["result"]["entries_added"]
    map_id = str(map_copy.map_id)
    assert _sample(samples, "monoloc_map_entries", map_id=map_id, map="street") == n
    assert _sample(samples, "monoloc_jobs", kind="ingest", state="done") == 1
    route = {"method": "POST", "route": "/v1/maps/{map_id}/localize", "status": "200"}
    assert _sample(samples, "monoloc_http_request_duration_seconds_count", **route) == 1
    assert _sample(samples, "monoloc_localize_stage_duration_seconds_count", stage="pnp") == 1
    frames = "monoloc_localize_frames_total"
    outcomes = ("hypotheses", "no_hypothesis", "shed", "failed")
    counted = {o: _sample(samples, frames, map_id=map_id, outcome=o) for o in outcomes}
    assert counted == {"hypotheses": 1, "no_hypothesis": 0, "shed": 0, "failed": 0}
    # a frame that is not an image fails, counted under its map
    bad = _localize(client_on_copy, map_copy.map_id, map_copy.keys, b"not an image")
    assert 400 <= bad.status_code < 500 and bad.status_code not in (401, 403, 404), bad.text
    samples = _samples(client_on_copy.get("/metrics", headers=admin).text)
    assert _sample(samples, frames, map_id=map_id, outcome="failed") == 1

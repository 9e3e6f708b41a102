"""Durable jobs: an ingestion cut off by a shutdown is handed back to the queue, one left
'running' by a crashed process is taken over by the restarted one; either keeps its
upload and resumes without duplicates; a cancelled job resumes when asked;
vocabulary training with an upload and a vocabulary change as a job."""

from __future__ import annotations

import time

import numpy as np
from api_helpers import (
    MAP_FRAMES,
    camera_of,
    create_keys,
    frame_png,
    ground_truth,
    make_settings,
    open_client,
    tar_sequence,
    wait_job,
)

from monoloc.core.geometry import planar_from_T_world_from_cam


def _upload(client, keys, dataset, **data):
    map_id = client.post(
        "/v1/maps", json={"name": "m", "camera": camera_of(dataset)}, headers=keys.header("admin")
    ).json()["id"]
    r = client.post(
        f"/v1/maps/{map_id}/runs",
        headers=keys.header("write"),
        files={"archive": ("m.tar.gz", tar_sequence(dataset), "application/gzip")},
        data={"format": "kitti", **data},
    )
    assert r.status_code == 202, r.text
    return map_id, r.json()["job"]["id"]


def test_interrupted_ingestion_resumes_without_duplicates(sim_dataset, tmp_path, monkeypatch):
    import monoloc.server.ingest.pipeline as pipeline

    build = pipeline.build_entry

    def slow_build(*args, **kwargs):  # ingestion slow enough to be cut off mid-run
        time.sleep(0.15)
        return build(*args, **kwargs)

    monkeypatch.setattr(pipeline, "build_entry", slow_build)
    settings = make_settings(tmp_path / "data")
    with open_client(settings) as client:
        keys = create_keys(client)
        map_id, job_id = _upload(client, keys, sim_dataset)
        deadline = time.monotonic() + 30
        while (
            client.get(f"/v1/jobs/{job_id}", headers=keys.header("write")).json()["progress"] == 0.0
        ):
            assert time.monotonic() < deadline
            time.sleep(0.02)
    # Shutdown asked the job to stop: it committed what it had and went back to the queue.
    import socket
    import subprocess
    import sys

    from monoloc.server.jobs import store as jobs_repo
    from monoloc.server.storage import entries as entries_repo
    from monoloc.server.storage.db import create_engine_for, make_session_factory, session_scope
    from monoloc.server.storage.models import Job

    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        text=True,
        capture_output=True,
        check=True,
    )
    engine = create_engine_for(settings)
    with session_scope(make_session_factory(engine)) as session:
        job = jobs_repo.get_job(session, job_id)
        assert job.state == "queued" and "handed back" in job.message, job
        # as if a process of this host had crashed holding it (a long lease, a dead pid)
        row = session.get(Job, job_id)
        row.state, row.lease_owner = "running", f"{socket.gethostname()}:{dead.stdout.strip()}:x"
        row.lease_expires_at = row.updated_at.replace(year=2100)
        partial = {"n_entries": entries_repo.count_entries(session, map_id)}
    engine.dispose()
    assert (tmp_path / "data" / "uploads" / str(job_id)).is_dir()

    monkeypatch.setattr(pipeline, "build_entry", build)
    with open_client(settings) as client:
        h = keys.header("write")
        assert 0 < partial["n_entries"] < MAP_FRAMES
        job = wait_job(client, job_id, h)  # taken over by the restarted process, unasked
        assert job["state"] == "done", job
        assert client.post(f"/v1/jobs/{job_id}/resume", headers=h).status_code == 409
        final = client.get(f"/v1/maps/{map_id}", headers=keys.header("admin")).json()
        run = client.get(f"/v1/maps/{map_id}/runs/{job['run_id']}", headers=h).json()
        listed = client.get(f"/v1/jobs?map_id={map_id}&state=done", headers=h).json()["items"]
    skipped = job["result"]["skip_reasons"]
    assert final["n_entries"] + skipped.get("too_few_points", 0) == MAP_FRAMES
    # The first attempt's entries are the run's own: counted as added, not as skipped, so
    # added + skipped = done = total in the job's result and on the run (issue 15, item 7).
    result = job["result"]
    assert result["entries_added"] == final["n_entries"] and "already_in_map" not in skipped
    assert result["entries_added"] + result["frames_skipped"] == result["frames_total"]
    assert result["frames_done"] == result["frames_total"] == MAP_FRAMES
    assert run["status"] == "done" and run["entries_added"] == final["n_entries"]
    assert run["entries_added"] + run["frames_skipped"] == run["frames_total"]
    assert [j["id"] for j in listed] == [job_id] and "upload" not in listed[0]["params"]
    assert not (tmp_path / "data" / "uploads" / str(job_id)).exists()


def test_trained_vocabulary_then_change_back(sim_dataset, tmp_path):
    with open_client(make_settings(tmp_path / "data")) as client:
        keys = create_keys(client)
        map_id, job_id = _upload(client, keys, sim_dataset, train_vocabulary="true")
        job = wait_job(client, job_id, keys.header("write"))
        assert job["state"] == "done", job
        trained = client.get(f"/v1/maps/{map_id}", headers=keys.header("admin")).json()
        assert trained["vocabulary"]["hash"] == job["result"]["vocabulary"]["vocabulary_hash"]
        assert f"m.tar.gz (job {job_id})" in trained["vocabulary"]["description"]
        assert str(tmp_path) not in trained["vocabulary"]["description"]

        r = client.post(
            f"/v1/maps/{map_id}/localize",
            headers=keys.header("localize"),
            files={"image": ("q.png", frame_png(sim_dataset, "01", 8), "image/png")},
        )
        best = r.json()["hypotheses"][0]
        truth = planar_from_T_world_from_cam(ground_truth(sim_dataset, "01", 8))
        assert np.hypot(best["pose"]["x_m"] - truth[0], best["pose"]["y_m"] - truth[1]) < 0.3

        r = client.post(
            f"/v1/maps/{map_id}/vocabulary/jobs",
            headers=keys.header("admin"),
            json={"vocabulary": "default"},
        )
        assert r.status_code == 202, r.text
        job = wait_job(client, r.json()["id"], keys.header("write"))
        assert job["state"] == "done", job
        assert job["result"]["recomputed"] == trained["n_entries"]
        back = client.get(f"/v1/maps/{map_id}", headers=keys.header("admin")).json()
        assert back["vocabulary"]["hash"] != trained["vocabulary"]["hash"]
        assert back["version"] > trained["version"]
        r = client.post(
            f"/v1/maps/{map_id}/vocabulary/jobs",
            headers=keys.header("admin"),
            json={"vocabulary": "00000000deadbeef"},
        )
        assert r.status_code == 404


def test_a_run_uploaded_with_register_reports_its_registration(sim_dataset, tmp_path):
    """The second run of the street, uploaded with register_to_map=true: its frames localized
    against the first run's entries, reported in the job's result (16 frames are fewer
    than the 20 the default asks for before moving a run, so it is reported, not moved)."""
    with open_client(make_settings(tmp_path / "data")) as client:
        keys = create_keys(client)
        map_id, job_id = _upload(client, keys, sim_dataset)
        assert wait_job(client, job_id, keys.header("write"))["result"]["registration"] is None

        def upload_query(**data):
            r = client.post(
                f"/v1/maps/{map_id}/runs",
                headers=keys.header("write"),
                files={
                    "archive": ("q.tar.gz", tar_sequence(sim_dataset, "01"), "application/gzip")
                },
                data={"format": "kitti", "kind": "offcenter", **data},
            )
            return r

        assert upload_query(register_to_map="perhaps").status_code == 422
        r = upload_query(register_to_map="true")
        assert r.status_code == 202, r.text
        job = wait_job(client, r.json()["job"]["id"], keys.header("write"))
        assert job["state"] == "done", job
        assert job["params"]["register_to_map"] is True
        reg = job["result"]["registration"]
        assert reg["frames_measured"] >= MAP_FRAMES // 2, reg
        assert reg["frames_used"] <= reg["frames_measured"] < 20
        assert reg["offset_max_m"] == 0.0
        assert len(reg["noise_m"]) == 2 and min(reg["noise_m"]) >= 0.01
        runs = client.get(f"/v1/maps/{map_id}/runs", headers=keys.header("write")).json()
        assert [r["registration"] for r in runs] == [None, reg]

"""Calibration jobs over HTTP: a training run uploaded like a mapping run (tar archive or
multipart file set) is fitted by a durable job whose parameters and provenance GET
/v1/maps/{id}/calibration then serves (calibrated: true), without adding the run to the
map; a too-short run is refused with 422 and a run without usable frames ends in a
failed job, neither storing anything; a cancelled calibration resumes.

The training run is the session's sim map run (16 full-size frames) with k = 5, so a
temporary map of 8 entries is queried by 8 frames.
"""

from __future__ import annotations

import io
import shutil
import tarfile
import time
from pathlib import Path

import numpy as np
import pytest
from api_helpers import tar_sequence, wait_job

TRAIN = {"format": "kitti", "k": "5"}


@pytest.fixture
def app(empty_map_app):
    return empty_map_app


def _post(client, keys, map_id, data=TRAIN, archive: bytes | None = None, files=None):
    if files is None:
        files = {} if archive is None else {"archive": ("train.tar.gz", archive, "x")}
    return client.post(
        f"/v1/maps/{map_id}/calibration/jobs", headers=keys.header("write"), data=data, files=files
    )


def _calibration(client, keys, map_id) -> dict:
    r = client.get(f"/v1/maps/{map_id}/calibration", headers=keys.header("localize"))
    assert r.status_code == 200, r.text
    return r.json()


def _nothing_stored(client, keys, map_id, data_dir: Path) -> None:
    assert _calibration(client, keys, map_id)["calibrated"] is False
    m = client.get(f"/v1/maps/{map_id}", headers=keys.header("admin")).json()
    assert m["n_entries"] == 0
    assert client.get(f"/v1/maps/{map_id}/runs", headers=keys.header("write")).json() == []


def test_uploaded_training_run_calibrates_the_map(app, sim_dataset):
    from monoloc.client.api import MonolocClient

    client, keys, map_id, data_dir = app
    r = _post(client, keys, map_id, archive=tar_sequence(sim_dataset, "00"))
    assert r.status_code == 202, r.text
    accepted = r.json()
    assert accepted["n_frames"] == 16 and accepted["job"]["kind"] == "calibrate"
    assert accepted["job"]["run_id"] is None and accepted["job"]["params"]["k"] == 5
    job = wait_job(client, accepted["job"]["id"], keys.header("write"))
    assert job["state"] == "done" and job["progress"] == 1.0, job

    got = _calibration(client, keys, map_id)
    assert got["calibrated"] is True and got["source"] == "calibrated" and got["updated_at"]
    prov = got["provenance"]
    m = client.get(f"/v1/maps/{map_id}", headers=keys.header("admin")).json()
    assert prov["source"] == "train.tar.gz" and prov["job_id"] == job["id"]
    assert (prov["frames"], prov["map_frames"], prov["query_frames"]) == (16, 8, 8)
    assert prov["used"] == prov["hypotheses"] - prov["gated_outliers"] >= 10
    assert prov["vocabulary_hash"] == m["vocabulary"]["hash"] and prov["created_at"]
    assert "unbiased" in prov["covariance"] and "truth - hypothesis" in prov["error_convention"]
    Sigma1 = np.array(got["Sigma1"])
    assert np.linalg.eigvalsh(Sigma1).min() > 0 and np.linalg.eigvalsh(got["Sigma2"]).min() > 0
    std_m = np.sqrt(np.diag(Sigma1)[:2])
    assert np.all((std_m > 0.01) & (std_m < 1.0)) and np.hypot(*got["mu1"][:2]) < 0.2
    assert job["result"]["mu1"] == got["mu1"] and job["result"]["provenance"] == prov
    # the training maps' VLAD distances between entries 2-6 m apart, for the fit check;
    # this map has no entries yet, so how the calibration fits it is not known
    assert prov["vlad_neighbours"]["n"] > 0 and 0.0 < prov["vlad_neighbours"]["mean"] < 2.0
    assert got["fit"]["map"]["n"] == 0 and got["fit"]["fits"] is None
    # the paper covariance's tail is set, not fitted, and recorded as such
    assert (got["tail_weight"], got["tail_scale"]) == (0.3, 10.0)
    assert job["result"]["tail_weight"] == 0.3 and "set, not fitted" in prov["paper_tail"]

    # The training run is not part of the map; its upload is gone once the job is done.
    assert m["n_entries"] == 0
    assert client.get(f"/v1/maps/{map_id}/runs", headers=keys.header("write")).json() == []
    # removed right after 'done' is committed (never before: a failed commit must leave
    # the upload for the replica that takes the job over)
    upload = data_dir / "uploads" / str(job["id"])
    deadline = time.monotonic() + 10
    while upload.exists():
        assert time.monotonic() < deadline, "the upload outlived its job"
        time.sleep(0.02)
    vehicle = MonolocClient("http://testserver", keys.localize, transport=client._transport)
    model, calibrated = vehicle.measurement_model(map_id)
    assert calibrated and np.allclose(model.Sigma1, Sigma1)
    assert (model.tail_weight, model.tail_scale) == (0.3, 10.0)
    # every model is fitted and stored; the product's, the PnP covariance model, is
    # selected: which one is no choice of the job
    assert model.covariance == "pnp" and model.pnp.pixel_std_px > 0
    assert model.quality is not None and job["result"]["pnp"] == got["pnp"]
    assert "covariance" not in job["params"] and "upload" not in job["params"]
    assert job["params"]["source_name"] == "train.tar.gz" and job["params"]["seed"] == 0


def test_too_short_a_run_is_refused_and_leaves_nothing(app, sim_dataset):
    client, keys, map_id, data_dir = app
    archive = tar_sequence(sim_dataset, "00")
    r = _post(client, keys, map_id, data={"format": "kitti"}, archive=archive)  # k = 10
    assert r.status_code == 422, r.text
    message = r.json()["error"]["message"]
    assert "too short to calibrate: 16 frames" in message and "at least 20" in message
    assert str(data_dir) not in message
    r = _post(client, keys, map_id, data={**TRAIN, "frames": "0:6"}, archive=archive)
    assert r.status_code == 422 and "6 frames" in r.json()["error"]["message"]
    assert _post(client, keys, map_id, data={**TRAIN, "k": "0"}, archive=archive).status_code == 422
    assert _post(client, keys, 999, archive=archive).status_code == 404
    assert _post(client, keys, map_id, archive=None).status_code == 422  # no upload at all
    assert client.get("/v1/jobs", headers=keys.header("write")).json()["items"] == []
    assert list((data_dir / "uploads").iterdir()) == []
    _nothing_stored(client, keys, map_id, data_dir)


def _blank_run(dataset: Path, tmp_path: Path) -> bytes:
    """The sim run with every image replaced by a flat gray one (no keypoints)."""
    import cv2

    root = tmp_path / "blank"
    shutil.copytree(dataset / "sequences" / "00", root / "sequences" / "00")
    shutil.copytree(dataset / "poses", root / "poses")
    for png in (root / "sequences" / "00" / "image_0").glob("*.png"):
        image = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(png), np.full_like(image, 128))
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz", compresslevel=1) as tar:
        tar.add(root, arcname="blank")
    return buffer.getvalue()


def test_run_without_usable_frames_fails_the_job_and_stores_nothing(app, sim_dataset, tmp_path):
    client, keys, map_id, data_dir = app
    r = _post(client, keys, map_id, archive=_blank_run(sim_dataset, tmp_path))
    assert r.status_code == 202, r.text
    job = wait_job(client, r.json()["job"]["id"], keys.header("write"))
    assert job["state"] == "failed", job
    assert "needs at least 5 map frames with 3D points" in job["error"]
    assert "got 0 map frames (8 without enough 3D points)" in job["error"]
    assert str(data_dir) not in job["error"]
    _nothing_stored(client, keys, map_id, data_dir)


def test_cancelled_calibration_resumes(app, sim_dataset, monkeypatch):
    """A file-set upload; the job is cancelled mid-run (slowed down to make that
    certain), ends interrupted with nothing stored, and a resume calibrates the map."""
    import monoloc.server.calibrate as calibration

    build = calibration.build_entry

    def slow_build(*args, **kwargs):
        time.sleep(0.2)
        return build(*args, **kwargs)

    monkeypatch.setattr(calibration, "build_entry", slow_build)
    client, keys, map_id, data_dir = app
    h = keys.header("write")
    seq = sim_dataset / "sequences" / "00"
    files = [
        ("files", (f"sequences/00/{p.relative_to(seq)}", p.read_bytes(), "x"))
        for p in sorted(seq.rglob("*"))
        if p.is_file()
    ]
    files.append(("files", ("poses/00.txt", (sim_dataset / "poses" / "00.txt").read_bytes(), "x")))
    r = _post(client, keys, map_id, files=files)
    assert r.status_code == 202, r.text
    job_id = r.json()["job"]["id"]
    deadline = time.monotonic() + 30
    while client.get(f"/v1/jobs/{job_id}", headers=h).json()["progress"] == 0.0:
        assert time.monotonic() < deadline
        time.sleep(0.02)
    assert client.post(f"/v1/jobs/{job_id}/cancel", headers=h).status_code == 200
    job = wait_job(client, job_id, h)
    assert job["state"] == "interrupted" and "resume" in job["message"], job
    assert (data_dir / "uploads" / str(job_id)).is_dir()
    _nothing_stored(client, keys, map_id, data_dir)

    monkeypatch.setattr(calibration, "build_entry", build)
    assert client.post(f"/v1/jobs/{job_id}/resume", headers=h).status_code == 200
    job = wait_job(client, job_id, h)
    assert job["state"] == "done", job
    got = _calibration(client, keys, map_id)
    assert got["calibrated"] is True and got["provenance"]["source"] == "files"

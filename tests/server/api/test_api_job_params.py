"""A job's parameters are one validated model per kind (monoloc.server.jobs.params): a bad
one is refused when the job is created (422 naming the field, before the upload is even
unpacked), and a row stored by an older server, in the shape its routes and CLI wrote,
still runs after an upgrade, or fails with the reason when it asked for what the server
no longer does. The API offers only the product's calibration choices."""

from __future__ import annotations

import shutil
from datetime import UTC, datetime
from pathlib import Path

import pytest
from api_helpers import MAP_FRAMES, make_settings, wait_job

from monoloc.core.errors import ConflictError
from monoloc.core.measurement import DEFAULT_RETRIEVAL_FRAME, DEFAULT_VLAD_EVIDENCE
from monoloc.server.jobs import store as jobs_repo
from monoloc.server.jobs.calibration import CalibrationParams
from monoloc.server.jobs.ingest import IngestParams
from monoloc.server.jobs.vocabulary import VocabularyParams
from monoloc.server.storage import maps as maps_repo
from monoloc.server.storage import runs as runs_repo
from monoloc.server.storage.db import create_engine_for, make_session_factory, session_scope
from monoloc.server.storage.records import JobRecord

# What the routes and `monoloc map calibrate` / `map vocab` wrote before the models,
# field for field (the oldest shape of each: no depth_from, register_to_map, condition).
OLD_INGEST = {
    "format": "kitti",
    "sequence": None,
    "frames": None,
    "tags": ["night"],
    "upload": True,
    "source_name": "old.tar.gz",
    "train_vocabulary": False,
}
OLD_CALIBRATION = {
    "format": "kitti",
    "sequence": "05",
    "frames": "0:40",
    "k": 5,
    "seed": 3,
    "upload": True,
    "source_name": "train.tar.gz",
}
OLD_CLI_CALIBRATION = {
    "format": "kitti",
    "path": "/data/kitti",
    "sequence": "05",
    "frames": None,
    "covariance": "pnp",
    "depth_from": "stereo",
    "source_name": "kitti 05",
    "k": 10,
    "seed": 0,
    "upload": False,
    "condition": "night",
}
OLD_VOCABULARY = {"vocabulary_id": 1, "vocabulary": "default"}
OLD_CLI_VOCABULARY = {"vocabulary": None, "train_from": "kitti 00", "max_images": 300, "seed": 0}


def _row(kind: str, params: dict, job_id: int = 7) -> JobRecord:
    now = datetime.now(UTC)
    return JobRecord(
        id=job_id,
        kind=kind,
        map_id=1,
        run_id=None,
        state="interrupted",
        progress=0.0,
        message="",
        error=None,
        params=params,
        result=None,
        created_at=now,
        updated_at=now,
        finished_at=None,
    )


def test_rows_of_the_old_shapes_parse_as_they_were_meant():
    ingest = IngestParams.from_row(_row("ingest", OLD_INGEST))
    assert (ingest.format, ingest.tags, ingest.depth_from) == ("kitti", ("night",), "lidar")
    assert not ingest.register_to_map and ingest.source_name == "old.tar.gz"
    calibration = CalibrationParams.from_row(_row("calibrate", OLD_CALIBRATION))
    assert (calibration.k, calibration.seed, calibration.condition) == (5, 3, None)
    assert calibration.config.k == 5 and calibration.frames == "0:40"
    cli = CalibrationParams.from_row(_row("calibrate", OLD_CLI_CALIBRATION))
    assert (cli.depth_from, cli.condition, cli.upload) == ("stereo", "night", False)
    chose_pnp = {**OLD_CALIBRATION, "covariance": "pnp"}  # the product's: it runs
    assert CalibrationParams.from_row(_row("calibrate", chose_pnp)) == calibration
    vocabulary = VocabularyParams.from_row(_row("vocabulary", OLD_VOCABULARY))
    assert (vocabulary.vocabulary_id, vocabulary.train) == (1, None)
    trained = VocabularyParams.from_row(_row("vocabulary", OLD_CLI_VOCABULARY))
    assert trained.train.run == "kitti 00" and trained.vocabulary_id is None
    assert (trained.train.max_images, trained.train.seed) == (300, 0)
    # today's rows read back as written
    for params in (ingest, calibration, cli, vocabulary, trained):
        stored = params.model_dump(mode="json")
        assert type(params).from_row(_row("any", stored)) == params


@pytest.mark.parametrize(
    "kind, params, named",
    [
        ("calibrate", {**OLD_CALIBRATION, "covariance": "paper"}, "'paper' pose-error model"),
        ("calibrate", {**OLD_CALIBRATION, "covariance": "quality"}, "'quality' pose-error model"),
        ("calibrate", {**OLD_CALIBRATION, "options": {}}, "options: Extra inputs"),
        ("ingest", {**OLD_INGEST, "format": "colmap"}, "format: Input should be"),
        ("ingest", {**OLD_INGEST, "tags": ["not a tag"]}, "tags: invalid tag"),
    ],
)
def test_a_row_this_server_cannot_run_is_refused_with_the_reason(kind, params, named):
    model = {"calibrate": CalibrationParams, "ingest": IngestParams}[kind]
    with pytest.raises(ConflictError, match="job 7") as refused:
        model.from_row(_row(kind, params))
    assert named in str(refused.value) and "create a new" in str(refused.value)


def _database(data_dir: Path):
    engine = create_engine_for(make_settings(data_dir))
    return engine, make_session_factory(engine)


def _stored_job(data_dir: Path, kind: str, map_id: int, params: dict, **kwargs) -> int:
    """A job row written as an older server left it: interrupted, with ``params`` as
    they are (no model checks them on the way in)."""
    engine, sessions = _database(data_dir)
    with session_scope(sessions) as session:
        job = jobs_repo.create_job(session, kind, map_id=map_id, params=params, **kwargs)
        jobs_repo.update_job(session, job.id, state="interrupted", message="server stopped")
    engine.dispose()
    return job.id


def test_a_bad_parameter_is_refused_when_the_job_is_created(empty_map_app):
    """Stereo depth for a TUM run: 422 naming depth_from before the upload (here not even
    an archive) is unpacked; no run, no job, no files."""
    client, keys, map_id, data_dir = empty_map_app
    r = client.post(
        f"/v1/maps/{map_id}/runs",
        headers=keys.header("write"),
        files={"archive": ("run.tar", b"not an archive at all", "application/x-tar")},
        data={"format": "tum", "depth_from": "stereo"},
    )
    assert r.status_code == 422, r.text
    message = r.json()["error"]["message"]
    assert message.startswith("invalid job parameter depth_from:") and "KITTI" in message
    assert client.get("/v1/jobs", headers=keys.header("write")).json()["items"] == []
    assert client.get(f"/v1/maps/{map_id}/runs", headers=keys.header("write")).json() == []
    uploads = data_dir / "uploads"
    assert not uploads.exists() or list(uploads.iterdir()) == []


def test_an_ingestion_stored_in_the_old_shape_resumes_after_an_upgrade(empty_map_app, sim_dataset):
    client, keys, map_id, data_dir = empty_map_app
    engine, sessions = _database(data_dir)
    with session_scope(sessions) as session:
        run = runs_repo.create_run(
            session, map_id, kind="night", source_format="kitti", source_name="old.tar.gz"
        )
    engine.dispose()
    job_id = _stored_job(data_dir, "ingest", map_id, OLD_INGEST, run_id=run.id)
    upload = data_dir / "uploads" / str(job_id) / "kitti"
    shutil.copytree(sim_dataset / "sequences" / "00", upload / "sequences" / "00")
    shutil.copytree(sim_dataset / "poses", upload / "poses")

    h = keys.header("write")
    assert client.post(f"/v1/jobs/{job_id}/resume", headers=h).status_code == 200
    job = wait_job(client, job_id, h)
    assert job["state"] == "done", job
    result = job["result"]
    assert result["entries_added"] + result["frames_skipped"] == MAP_FRAMES
    assert job["params"] == {k: v for k, v in OLD_INGEST.items() if k != "upload"}
    tags = client.get(f"/v1/maps/{map_id}", headers=keys.header("admin")).json()["tag_counts"]
    assert tags == {"night": result["entries_added"]}


def test_old_rows_that_cannot_run_fail_with_the_reason(empty_map_app):
    """A calibration that chose the paper's model, and a vocabulary change of the CLI
    (which the runner cannot redo), resumed after an upgrade; a vocabulary change stored
    by the route in its old shape runs."""
    client, keys, map_id, data_dir = empty_map_app
    h = keys.header("write")
    paper = _stored_job(data_dir, "calibrate", map_id, {**OLD_CALIBRATION, "covariance": "paper"})
    (data_dir / "uploads" / str(paper)).mkdir(parents=True)
    cli = _stored_job(data_dir, "vocabulary", map_id, OLD_CLI_VOCABULARY)
    engine, sessions = _database(data_dir)
    with session_scope(sessions) as session:
        vocabulary_id = maps_repo.get_map(session, map_id).vocabulary_id
    engine.dispose()
    stored = {**OLD_VOCABULARY, "vocabulary_id": vocabulary_id}
    route = _stored_job(data_dir, "vocabulary", map_id, stored)

    for job_id in (paper, cli, route):
        assert client.post(f"/v1/jobs/{job_id}/resume", headers=h).status_code == 200
    failed = wait_job(client, paper, h)
    assert failed["state"] == "failed", failed
    assert "select the 'paper' pose-error model" in failed["error"]
    assert "this server selects 'pnp': create a new calibration job" in failed["error"]
    failed = wait_job(client, cli, h)
    assert failed["state"] == "failed" and "`monoloc map vocab`" in failed["error"], failed
    done = wait_job(client, route, h)
    assert done["state"] == "done" and done["result"]["vocabulary_id"] == vocabulary_id, done


def test_the_api_offers_only_the_products_calibration_choices(fresh):
    client, _ = fresh
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    update = schemas["CalibrationUpdate"]["properties"]
    # The lab's variants (vehicle-frame offsets, relative VLAD evidence) are not offered:
    # a GET's body may be PUT back, so the fields are stated, with the product's value only.
    for name, product in (
        ("retrieval_frame", DEFAULT_RETRIEVAL_FRAME),
        ("vlad_evidence", DEFAULT_VLAD_EVIDENCE),
    ):
        offered = {v.get("const", v.get("type")) for v in update[name]["anyOf"]}
        assert offered == {product, "null"}, (name, update[name])
    choices = {e for v in update["covariance"]["anyOf"] for e in v.get("enum", [None])}
    assert choices == {"paper", "pnp", None}
    form = next(v for k, v in schemas.items() if k.startswith("Body_calibration_job"))
    assert set(form["properties"]) == {
        "format", "archive", "files", "sequence", "frames", "k", "seed", "condition"
    }  # fmt: skip

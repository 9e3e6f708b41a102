import pytest

from monoloc.core.errors import ConflictError, InvalidInputError
from monoloc.server.jobs.store import (
    create_job,
    get_job,
    list_jobs,
    mark_interrupted_jobs,
    update_job,
)
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.keys import (
    create_api_key,
    list_api_keys,
    revoke_api_key,
    verify_api_key,
)
from monoloc.server.storage.models import ApiKey
from monoloc.server.storage.runs import create_run, get_run, update_run


def test_job_lifecycle_and_forbidden_transitions(factory, map_id):
    with session_scope(factory) as session:
        job = create_job(session, "ingest", map_id=map_id, params={"format": "kitti"})
        assert (job.state, job.progress, job.finished_at) == ("queued", 0.0, None)
        update_job(session, job.id, state="running", progress=0.25, message="frame 10/40")
        with pytest.raises(InvalidInputError):
            update_job(session, job.id, progress=1.5)
        done = update_job(session, job.id, state="done", result={"entries_added": 40})
        assert done.progress == 1.0 and done.finished_at is not None
        with pytest.raises(ConflictError):
            update_job(session, job.id, state="running")
    with session_scope(factory) as session:
        assert get_job(session, job.id).result == {"entries_added": 40}
        assert [j.id for j in list_jobs(session, map_id=map_id, states=["done"])] == [job.id]


def test_interrupted_jobs_are_marked_on_startup_and_can_resume(factory, map_id):
    with session_scope(factory) as session:
        run = create_run(session, map_id, kind="map", source_format="kitti", frames_total=40)
        update_run(session, run.id, status="running", frames_done=12, skip_reasons={"no pose": 2})
        running = create_job(session, "ingest", map_id=map_id, run_id=run.id)
        update_job(session, running.id, state="running", progress=0.3)
        queued = create_job(session, "ingest", map_id=map_id)
        finished = create_job(session, "vocab", map_id=map_id)
        update_job(session, finished.id, state="failed", error="boom")
    # --- the server restarts ---
    with session_scope(factory) as session:
        assert sorted(mark_interrupted_jobs(session)) == sorted([running.id, queued.id])
    with session_scope(factory) as session:
        states = {j.id: j.state for j in list_jobs(session)}
        assert states == {
            running.id: "interrupted",
            queued.id: "interrupted",
            finished.id: "failed",
        }
        resumed = get_job(session, running.id)
        assert resumed.progress == 0.3 and "interrupted" in resumed.message
        assert get_run(session, run.id).status == "interrupted"
        assert get_run(session, run.id).skip_reasons == {"no pose": 2}
        again = update_job(session, running.id, state="running")
        assert again.finished_at is None
        assert mark_interrupted_jobs(session) == [running.id]


def test_api_keys_verify_reject_and_revoke(factory):
    with session_scope(factory) as session:
        record, key = create_api_key(session, "vehicle-7", "localize,map:write")
        admin, admin_key = create_api_key(session, "ops", ["admin"])
        with pytest.raises(InvalidInputError, match="unknown scope"):
            create_api_key(session, "x", ["root"])
    assert key.startswith("mlk_") and len(key) > 40
    with session_scope(factory) as session:
        stored = session.get(ApiKey, record.id)
        assert key not in (stored.key_hash, stored.prefix) and len(stored.key_hash) == 64
        ok = verify_api_key(session, key)
        assert ok is not None and ok.scopes == {"localize", "map:write"}
        assert ok.has_scope("localize") and not ok.has_scope("admin")
        assert verify_api_key(session, admin_key).has_scope("map:write")  # admin implies all
        wrong = key[:-1] + ("A" if key[-1] != "A" else "B")  # same prefix, wrong secret
        assert verify_api_key(session, wrong) is None
        assert verify_api_key(session, "") is None and verify_api_key(session, "Bearer x") is None
        revoke_api_key(session, record.id)
    with session_scope(factory) as session:
        assert verify_api_key(session, key) is None
        assert verify_api_key(session, admin_key) is not None
        assert [k.revoked for k in list_api_keys(session)] == [True, False]
        assert [k.id for k in list_api_keys(session, include_revoked=False)] == [admin.id]

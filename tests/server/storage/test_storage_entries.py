import numpy as np
import pytest
from sqlalchemy import func, select

from monoloc.core.camera import KITTI_CAM0
from monoloc.core.errors import ConflictError, InvalidInputError, NotFoundError
from monoloc.server.jobs.store import create_job, get_job
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.entries import (
    add_entry,
    count_entries,
    delete_entry,
    existing_entry_data,
    existing_hashes,
    get_entry,
    get_entry_data,
    iter_map_vectors,
    list_entries,
    set_entry_tags,
    tag_counts,
    update_entry_vlad,
)
from monoloc.server.storage.maps import (
    create_map,
    delete_map,
    get_map,
    get_or_create_vocabulary,
    list_maps,
    set_calibration,
    set_map_vocabulary,
)
from monoloc.server.storage.models import Entry, EntryTag, Run
from monoloc.server.storage.records import Area
from monoloc.server.storage.runs import create_run


def test_add_entry_is_idempotent_by_source_hash_and_bumps_version(factory, map_id, make_entry):
    with session_scope(factory) as session:
        first, created = add_entry(session, map_id, make_entry("a", tags=("Night",)))
        assert created and first.tags == ("night",)
        assert get_map(session, map_id).version == 1
    with session_scope(factory) as session:
        again, created = add_entry(session, map_id, make_entry("a", x_m=50.0))
        assert not created and again.id == first.id and again.x_m == first.x_m
        add_entry(session, map_id, make_entry("b"))
    with session_scope(factory) as session:
        record = get_map(session, map_id)
        assert (record.version, record.n_entries) == (2, 2)
        assert existing_hashes(session, map_id, [first.source_image_hash, "0" * 64]) == {
            first.source_image_hash
        }


def test_filters_and_pagination(factory, map_id, make_entry):
    with session_scope(factory) as session:
        run = create_run(session, map_id, kind="night", source_format="kitti", source_name="00")
        for i in range(10):
            tags = ("night",) if i % 2 else ("off-center",)
            add_entry(
                session,
                map_id,
                make_entry(f"f{i}", x_m=float(i), y_m=0.0, tags=tags),
                run_id=run.id if i < 3 else None,
            )
    with session_scope(factory) as session:
        assert [e.x_m for e in list_entries(session, map_id, tag="NIGHT")] == [1, 3, 5, 7, 9]
        assert count_entries(session, map_id, run_id=run.id) == 3
        # x = 3 and x = 5 are 1.118 m from (4, 0.5): outside the disc, inside its box.
        near = list_entries(session, map_id, area=Area(x_m=4.0, y_m=0.5, radius_m=1.11))
        assert [e.x_m for e in near] == [4.0]
        assert count_entries(session, map_id, area=Area(4.0, 0.5, 1.12)) == 3
        page = list_entries(session, map_id, limit=3, offset=3)
        assert [e.x_m for e in page] == [3.0, 4.0, 5.0]
        assert tag_counts(session, map_id) == {"night": 5, "off-center": 5}
        retagged = set_entry_tags(session, page[0].id, ["day", "Night", "day"])
        assert retagged.tags == ("day", "night")
        with pytest.raises(InvalidInputError, match="invalid tag"):
            set_entry_tags(session, page[0].id, ["bad tag"])
        vectors = list(iter_map_vectors(session, map_id, batch_size=4))
        assert [len(v.entry_ids) for v in vectors] == [4, 4, 2]
        assert np.allclose(np.concatenate([v.planar[:, 0] for v in vectors]), np.arange(10))
        # what a run registering to the map reads: other runs' entries near its path
        others = list(iter_map_vectors(session, map_id, exclude_run_id=run.id))
        assert np.allclose(np.concatenate([v.planar[:, 0] for v in others]), np.arange(3, 10))
        boxed = iter_map_vectors(session, map_id, exclude_run_id=run.id, within_m=(1.5, 6.2, -1, 1))
        assert np.allclose(np.concatenate([v.planar[:, 0] for v in boxed]), [3, 4, 5, 6])
        outside = list(iter_map_vectors(session, map_id, within_m=(0, 9, 1.0, 2.0)))
        assert sum(len(v.entry_ids) for v in outside) == 0


def test_delete_entry_bumps_version(factory, map_id, make_entry):
    with session_scope(factory) as session:
        entry = add_entry(session, map_id, make_entry("a", tags=("night",)))[0]
        kept = add_entry(session, map_id, make_entry("b"))[0]
    with session_scope(factory) as session:
        assert delete_entry(session, entry.id, map_id=map_id) == 3
        # an index may still list the deleted entry: the lookup that tolerates it
        rows = existing_entry_data(session, [kept.id, entry.id, kept.id])
        assert [r.id for r in rows] == [kept.id, kept.id]
        with pytest.raises(NotFoundError):
            get_entry_data(session, [entry.id])
        with pytest.raises(NotFoundError):
            get_entry(session, entry.id)
        with pytest.raises(NotFoundError):
            delete_entry(session, entry.id)
        assert session.scalar(select(func.count()).select_from(EntryTag)) == 0


def test_deleting_a_map_cascades_to_runs_entries_and_tags(factory, map_id, make_entry):
    with session_scope(factory) as session:
        run = create_run(session, map_id, kind="map", source_format="tum")
        for i in range(3):
            add_entry(session, map_id, make_entry(f"e{i}", tags=("night",)), run_id=run.id)
        job = create_job(session, "ingest", map_id=map_id, run_id=run.id)
    with session_scope(factory) as session:
        delete_map(session, map_id)
    with session_scope(factory) as session:
        for model in (Entry, EntryTag, Run):
            assert session.scalar(select(func.count()).select_from(model)) == 0
        assert list_maps(session) == []
        orphan = get_job(session, job.id)  # job history survives, detached from the map
        assert orphan.map_id is None and orphan.run_id is None
        with pytest.raises(NotFoundError):
            delete_map(session, map_id)


def test_failed_transaction_leaves_committed_data_intact(factory, map_id, make_entry):
    with session_scope(factory) as session:
        add_entry(session, map_id, make_entry("kept"))
    with pytest.raises(RuntimeError):
        with session_scope(factory) as session:
            add_entry(session, map_id, make_entry("lost"))
            raise RuntimeError("ingestion crashed mid-batch")
    bad = make_entry("nan-pose")
    bad.T_world_from_cam[0, 3] = np.nan
    with pytest.raises(InvalidInputError, match="NaN"):
        with session_scope(factory) as session:
            add_entry(session, map_id, bad)
    with session_scope(factory) as session:
        assert [e.source_image_hash for e in list_entries(session, map_id)] == [
            make_entry("kept").source_image_hash
        ]
        assert get_map(session, map_id).version == 1


def test_map_names_vocabularies_and_calibration(factory, map_id, make_entry):
    with session_scope(factory) as session:
        vocab_id = get_map(session, map_id).vocabulary_id
        with pytest.raises(ConflictError):
            create_map(session, "m", KITTI_CAM0, vocab_id)
        with pytest.raises(InvalidInputError):
            create_map(session, "no spaces", KITTI_CAM0, vocab_id)
        other = create_map(session, "m2", KITTI_CAM0, vocab_id)  # session still usable
        assert other.version == 0 and other.camera == KITTI_CAM0

        centres = np.random.default_rng(5).uniform(0, 255, (64, 32))
        vocab, created = get_or_create_vocabulary(session, centres, "retrained")
        assert created and get_or_create_vocabulary(session, centres)[1] is False
        entry = add_entry(session, map_id, make_entry("a"))[0]
        assert set_map_vocabulary(session, map_id, vocab.id).version == 2
        version = update_entry_vlad(
            session,
            entry.id,
            vlad=np.ones(2048),
            code=np.zeros(256, np.uint8),
            vocabulary_id=vocab.id,
        )
        assert version == 3 and get_entry(session, entry.id).vocabulary_id == vocab.id

        calibration = {
            "mu1": [0.1, 0.0, 0.01],
            "Sigma1": np.diag([0.2, 0.2, 0.05]).tolist(),
            "mu2": [0.5, 0.0, 0.0, 0.0],
            "Sigma2": np.diag([0.1, 4.0, 4.0, 0.3]),
            "provenance": {"sequence": "01", "n_samples": 812},
        }
        stored = set_calibration(session, map_id, calibration).calibration
        assert stored["provenance"]["n_samples"] == 812
        assert stored["Sigma2"][1][1] == 4.0
        with pytest.raises(InvalidInputError, match="positive definite"):
            set_calibration(session, map_id, {**calibration, "Sigma1": np.zeros((3, 3))})
        with pytest.raises(InvalidInputError, match="missing 'mu2'"):
            set_calibration(session, map_id, {"mu1": [0, 0, 0], "Sigma1": np.eye(3)})
    with session_scope(factory) as session:
        assert get_map(session, map_id).calibration["mu1"] == [0.1, 0.0, 0.01]
        assert set_calibration(session, map_id, None).calibration is None


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("points_cam", -np.ones((20, 3), np.float32), "in front of the camera"),
        ("keypoints_px", np.full((20, 2), 5000.0, np.float32), "outside"),
        ("descriptors", np.zeros((19, 32), np.uint8), "same N"),
        ("source_image_hash", "not-a-hash", "sha256"),
        ("T_world_from_cam", np.ones((4, 4)), "rigid"),
    ],
)
def test_invalid_entries_are_rejected(factory, map_id, make_entry, field, value, message):
    import dataclasses

    bad = dataclasses.replace(make_entry("x"), **{field: value})
    with session_scope(factory) as session:
        with pytest.raises(InvalidInputError, match=message):
            add_entry(session, map_id, bad)
        assert count_entries(session, map_id) == 0

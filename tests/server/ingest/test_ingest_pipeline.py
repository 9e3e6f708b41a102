"""The ingestion pipeline on the hand-made KITTI sequence: geometry of the stored 3D
points, idempotency, resuming, bad frames in the middle, and the live index."""

from __future__ import annotations

import numpy as np
import pytest

from monoloc.core.errors import InputFileError
from monoloc.core.geometry import zup_to_kitti
from monoloc.server.ingest.pipeline import IngestConfig, ingest_run
from monoloc.server.ingest.sources import read_kitti_sequence
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage import runs as runs_repo
from monoloc.server.storage.db import session_scope


def _entries(factory, map_id):
    with session_scope(factory) as session:
        ids = [e.id for e in entries_repo.list_entries(session, map_id, limit=1000)]
        return entries_repo.get_entry_data(session, ids)


def _run(factory, run_id):
    with session_scope(factory) as session:
        return runs_repo.get_run(session, run_id)


def test_ingested_points_reproject_and_lie_on_the_wall(kitti_root, factory, make_map, make_run):
    seq = read_kitti_sequence(kitti_root.root)
    map_id = make_map()
    summary = ingest_run(factory, map_id, seq, run_id=make_run(map_id, seq), tags=("day",))
    assert summary.entries_added == 8 and summary.frames_skipped == 0
    assert summary.points_min >= 300 and summary.points_mean >= summary.points_min
    entries = _entries(factory, map_id)
    assert len(entries) == 8
    K = kitti_root.camera.K
    for entry, T_true in zip(entries, kitti_root.T_kitti_from_cam, strict=True):
        # In its own image: each 3D point projects onto its keypoint (within 1 px).
        uvw = entry.points_cam.astype(np.float64) @ K.T
        error_px = np.linalg.norm(uvw[:, :2] / uvw[:, 2:] - entry.keypoints_px, axis=1)
        assert error_px.max() < 1.0
        # In the world: on the wall z = 8 m of KITTI's world, and the stored pose converts
        # back to the true KITTI pose.
        T_kitti = zup_to_kitti(entry.T_world_from_cam)
        np.testing.assert_allclose(T_kitti, T_true, atol=1e-6)
        points_kitti = entry.points_cam @ T_kitti[:3, :3].T + T_kitti[:3, 3]
        assert np.abs(points_kitti[:, 2] - kitti_root.wall_z_m).max() < 0.01
        assert entry.summary.tags == ("day",)
    run = _run(factory, summary.run_id)
    assert (run.status, run.frames_done, run.entries_added) == ("done", 8, 8)


def test_second_ingestion_adds_nothing(kitti_root, factory, make_map, make_run):
    seq = read_kitti_sequence(kitti_root.root)
    map_id = make_map()
    first = ingest_run(factory, map_id, seq, run_id=make_run(map_id, seq))
    second = ingest_run(factory, map_id, seq, run_id=make_run(map_id, seq))
    assert first.entries_added == 8
    assert second.entries_added == 0 and second.skip_reasons == {"already_in_map": 8}
    assert second.map_version == first.map_version
    assert len(_entries(factory, map_id)) == 8


def test_interrupted_ingestion_resumes_without_duplicates(kitti_root, factory, make_map, make_run):
    seq = read_kitti_sequence(kitti_root.root)
    map_id = make_map()
    run_id = make_run(map_id, seq)
    calls = []
    stop_after_three = lambda: bool(calls) and calls[-1][0] >= 3  # noqa: E731
    summary = ingest_run(
        factory,
        map_id,
        seq,
        run_id=run_id,
        should_stop=stop_after_three,
        progress=lambda done, total: calls.append((done, total)),
        config=IngestConfig(batch_size=2),
    )
    assert summary.interrupted and summary.entries_added == 3
    assert calls[0] == (0, 8) and calls[-1] == (3, 8)
    assert _run(factory, run_id).status == "interrupted"
    resumed = ingest_run(factory, map_id, seq, run_id=run_id)
    # The 3 frames of the first attempt are this run's entries, not skips: the counters
    # add up (added + skipped = done = total), in the summary and on the run.
    assert resumed.entries_added == 8 and resumed.skip_reasons == {}
    assert resumed.frames_done == resumed.frames_total == 8
    hashes = [e.summary.source_image_hash for e in _entries(factory, map_id)]
    assert len(hashes) == len(set(hashes)) == 8
    run = _run(factory, run_id)
    assert (run.entries_added, run.frames_skipped, run.frames_done) == (8, 0, 8)


def test_unreadable_image_fails_naming_it_and_keeps_earlier_frames(
    kitti_copy, factory, make_map, make_run
):
    bad = kitti_copy.sequence_dir / "image_0" / "000005.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 50)
    seq = read_kitti_sequence(kitti_copy.root)  # metadata is fine: this passes
    map_id = make_map()
    run_id = make_run(map_id, seq)
    with pytest.raises(InputFileError, match=r"image_0/000005\.png: unreadable image"):
        ingest_run(factory, map_id, seq, run_id=run_id, config=IngestConfig(batch_size=2))
    # Frames 0-4 came before the bad one: committed and kept.
    assert sorted(e.summary.timestamp_s for e in _entries(factory, map_id)) == pytest.approx(
        [0.0, 0.1, 0.2, 0.3, 0.4]
    )
    run = _run(factory, run_id)
    assert run.status == "failed" and "000005.png" in run.error


def test_skip_bad_frames_reports_them(kitti_copy, factory, make_map, make_run):
    (kitti_copy.sequence_dir / "image_0" / "000002.png").write_bytes(b"not an image")
    scan = kitti_copy.sequence_dir / "velodyne" / "000006.bin"
    scan.write_bytes(np.zeros((10, 4), dtype=np.float32).tobytes())  # nothing in view
    seq = read_kitti_sequence(kitti_copy.root)
    map_id = make_map()
    summary = ingest_run(
        factory,
        map_id,
        seq,
        run_id=make_run(map_id, seq),
        config=IngestConfig(skip_bad_frames=True),
    )
    assert summary.entries_added == 6
    assert summary.skip_reasons == {"unreadable_image": 1, "too_few_points": 1}
    assert _run(factory, summary.run_id).skip_reasons == summary.skip_reasons


def test_bad_metadata_fails_before_writing_and_keeps_earlier_data(
    kitti_copy, factory, make_map, make_run
):
    from monoloc.server.ingest.common import parse_frame_range

    first = read_kitti_sequence(kitti_copy.root, frames=parse_frame_range(":4"))
    map_id = make_map()
    ingest_run(factory, map_id, first, run_id=make_run(map_id, first))
    poses = kitti_copy.root / "poses" / "00.txt"
    lines = poses.read_text().splitlines()
    lines[6] = lines[6].replace(lines[6].split()[3], "nan", 1)
    poses.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputFileError, match=r"00\.txt:7:"):
        read_kitti_sequence(kitti_copy.root)
    assert len(_entries(factory, map_id)) == 4


def test_registry_sees_new_entries_at_once(kitti_root, factory, make_map, make_run, settings):
    from monoloc.server.map_registry import MapRegistry

    seq = read_kitti_sequence(kitti_root.root)
    map_id = make_map()
    registry = MapRegistry(factory, settings.index_dir, version_check_s=3600.0)
    assert len(registry.get(map_id).index) == 0  # loaded (empty) before the ingestion
    summary = ingest_run(
        factory,
        map_id,
        seq,
        run_id=make_run(map_id, seq),
        registry=registry,
        config=IngestConfig(batch_size=3),
    )
    runtime = registry.get(map_id)  # no reload: the version check is an hour away
    assert len(runtime.index) == 8 and runtime.version == summary.map_version
    assert registry.index_path(map_id).exists()  # persisted at the end

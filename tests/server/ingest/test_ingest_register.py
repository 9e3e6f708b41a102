"""Registering a run to the map it is added to: a second recording of the wall whose
navigation is off by a known shift is moved back onto the first run's frame."""

from __future__ import annotations

import cv2
import numpy as np

from monoloc.core.geometry import zup_to_kitti
from monoloc.core.registration import RegistrationConfig
from monoloc.server.ingest.pipeline import IngestConfig, ingest_run
from monoloc.server.ingest.sources import read_kitti_sequence
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage import runs as runs_repo
from monoloc.server.storage.db import session_scope

SHIFT_KITTI_M = np.array([0.20, 0.0, -0.12])  # x right, z forward: both horizontal
# The hand-made run has 8 frames: let 3 of them be enough evidence.
REGISTER = RegistrationConfig(min_frames=3)


def _second_recording(copy, rng) -> None:
    """Other exposure and sensor noise (so other images, not the same frames again), and
    written poses off by SHIFT_KITTI_M."""
    for path in sorted((copy.sequence_dir / "image_0").glob("*.png")):
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE).astype(np.float64)
        image = 0.85 * image + 20.0 + 2.0 * rng.standard_normal(image.shape)
        cv2.imwrite(str(path), np.clip(image, 0, 255).astype(np.uint8))
    poses_path = copy.root / "poses" / "00.txt"
    rows = np.loadtxt(poses_path).reshape(-1, 3, 4)
    rows[:, :, 3] += SHIFT_KITTI_M
    poses_path.write_text("".join(" ".join(f"{v:.9e}" for v in r.ravel()) + "\n" for r in rows))


def _position_errors_m(factory, map_id, run_id, T_true_kitti) -> np.ndarray:
    with session_scope(factory) as session:
        listed = entries_repo.list_entries(session, map_id, limit=1000)
        ids = [e.id for e in listed if e.run_id == run_id]
        entries = entries_repo.get_entry_data(session, ids)
    assert len(entries) == len(T_true_kitti)
    return np.array(
        [
            np.linalg.norm(zup_to_kitti(e.T_world_from_cam)[:3, 3] - T[:3, 3])
            for e, T in zip(entries, T_true_kitti, strict=True)
        ]
    )


def test_a_shifted_second_run_is_moved_onto_the_map(
    kitti_root, kitti_copy, factory, make_map, make_run
):
    _second_recording(kitti_copy, np.random.default_rng(0))
    first = read_kitti_sequence(kitti_root.root)
    second = read_kitti_sequence(kitti_copy.root)
    shift = np.linalg.norm(SHIFT_KITTI_M)

    registered_map = make_map(name="registered")
    ingest_run(factory, registered_map, first, run_id=make_run(registered_map, first))
    run_id = make_run(registered_map, second, "night")
    summary = ingest_run(
        factory, registered_map, second, run_id=run_id, config=IngestConfig(register=REGISTER)
    )
    assert summary.entries_added == 8
    reg = summary.registration
    assert reg is not None and reg["frames_used"] >= 3
    assert abs(np.linalg.norm(reg["offset_mean_m"]) - shift) < 0.03
    errors = _position_errors_m(factory, registered_map, run_id, kitti_root.T_kitti_from_cam)
    assert errors.max() < 0.03, errors
    with session_scope(factory) as session:  # the run keeps how it was registered
        assert runs_repo.get_run(session, run_id).registration == reg

    # The same upload without registration keeps the written (shifted) poses.
    plain_map = make_map(name="plain")
    ingest_run(factory, plain_map, first, run_id=make_run(plain_map, first))
    plain_run = make_run(plain_map, second, "night")
    plain = ingest_run(factory, plain_map, second, run_id=plain_run)
    assert plain.registration is None
    with session_scope(factory) as session:
        assert runs_repo.get_run(session, plain_run).registration is None
    errors = _position_errors_m(factory, plain_map, plain_run, kitti_root.T_kitti_from_cam)
    np.testing.assert_allclose(errors, shift, atol=1e-6)


def test_the_first_run_of_a_map_has_nothing_to_register_to(kitti_root, factory, make_map, make_run):
    seq = read_kitti_sequence(kitti_root.root)
    map_id = make_map()
    run_id = make_run(map_id, seq)
    summary = ingest_run(
        factory, map_id, seq, run_id=run_id, config=IngestConfig(register=REGISTER)
    )
    assert summary.entries_added == 8
    assert summary.registration["frames_measured"] == 0
    errors = _position_errors_m(factory, map_id, run_id, kitti_root.T_kitti_from_cam)
    assert errors.max() < 1e-6


def test_a_resumed_run_is_registered_to_the_other_runs_only(
    kitti_root, kitti_copy, factory, make_map, make_run
):
    """Its own entries from an earlier attempt are not evidence: the resumed attempt
    measures against the same entries with the same seed, so it finds the same correction
    and the run's entries from both attempts sit in one frame."""
    _second_recording(kitti_copy, np.random.default_rng(1))
    first = read_kitti_sequence(kitti_root.root)
    map_id = make_map()
    ingest_run(factory, map_id, first, run_id=make_run(map_id, first))
    second = read_kitti_sequence(kitti_copy.root)
    run_id = make_run(map_id, second)
    config = IngestConfig(register=REGISTER, batch_size=2)
    # registration polls once per frame (8), then the build loop a few times
    stops = iter([False] * 11 + [True] * 1000)
    interrupted = ingest_run(
        factory, map_id, second, run_id=run_id, config=config, should_stop=lambda: next(stops)
    )
    assert interrupted.interrupted and 0 < interrupted.entries_added < 8
    resumed = ingest_run(factory, map_id, second, run_id=run_id, config=config)
    assert resumed.entries_added == 8 and resumed.registration["frames_used"] >= 3
    assert resumed.registration == interrupted.registration
    errors = _position_errors_m(factory, map_id, run_id, kitti_root.T_kitti_from_cam)
    assert errors.max() < 0.03, errors


def test_map_ingest_register_prints_the_registration(kitti_root, kitti_copy, tmp_path):
    from typer.testing import CliRunner

    from monoloc import cli

    cli._register()
    _second_recording(kitti_copy, np.random.default_rng(2))
    env = {"MONOLOC_DATA_DIR": str(tmp_path / "data"), "COLUMNS": "200"}
    calib = str(kitti_root.sequence_dir / "calib.txt")

    def run(*args):
        result = CliRunner().invoke(cli.app, list(args), env=env, catch_exceptions=False)
        assert result.exit_code == 0, result.output
        return " ".join(result.output.split())

    run("map", "create", "wall", "--camera", calib)
    assert "registered" not in run("map", "ingest", "--map", "wall", str(kitti_root.root))
    out = run(
        "map", "ingest", "--map", "wall", str(kitti_copy.root), "--kind", "night", "--register"
    )
    # 8 frames: fewer than the 20 the default needs before it moves a run
    assert "registered to the map" in out and "localized frames used; not moved" in out
    stats = run("map", "stats", "wall")
    assert "registered" in stats and "localized frames used; not moved" in stats


def test_the_measurement_does_not_depend_on_the_number_of_threads(kitti_root, kitti_copy):
    from bench.lab.evaluation import MemoryMap
    from monoloc.server.ingest.register import RegistrationTarget, measure_offsets
    from monoloc.server.vision.vocabulary import load_default_vocabulary

    _second_recording(kitti_copy, np.random.default_rng(3))
    memory = MemoryMap.empty(load_default_vocabulary())
    memory.add_run(read_kitti_sequence(kitti_root.root))
    second = read_kitti_sequence(kitti_copy.root)
    runs = [
        measure_offsets(
            second,
            RegistrationTarget(memory.vocabulary, memory.index, memory.lookup),
            np.random.default_rng(7),
            REGISTER,
            workers=workers,
        )
        for workers in (1, 2)
    ]
    (t1, d1), (t2, d2) = runs
    assert len(t1) >= 3
    np.testing.assert_array_equal(t1, t2)
    np.testing.assert_array_equal(d1, d2)
    # each measured offset is the shift undone (KITTI x right = world -y, z forward = world x)
    np.testing.assert_allclose(np.median(d1, axis=0), [0.12, 0.20], atol=0.03)


def test_the_in_memory_map_registers_a_run_as_ingestion_does(kitti_root, kitti_copy):
    """bench.lab.evaluation (the benchmark's engine) registers through the same code."""
    from bench.lab.evaluation import MemoryMap
    from monoloc.server.vision.vocabulary import load_default_vocabulary

    _second_recording(kitti_copy, np.random.default_rng(4))
    memory = MemoryMap.empty(load_default_vocabulary())
    memory.add_run(read_kitti_sequence(kitti_root.root))
    added = memory.add_run(read_kitti_sequence(kitti_copy.root), register=REGISTER)
    assert added == 8 and memory.corrections[-1].used >= 3
    moved = [memory.refs[i].T_world_from_cam for i in range(8, 16)]
    truth = [memory.refs[i].T_world_from_cam for i in range(8)]
    errors = [np.linalg.norm(a[:3, 3] - b[:3, 3]) for a, b in zip(moved, truth, strict=True)]
    assert max(errors) < 0.03, errors


def test_a_tum_run_is_registered_too(kitti_root, tum_run):
    """The same wall as a TUM RGB-D run with its ground truth off by a known shift is
    moved back onto the KITTI run's map (another reader's frames, copied with new poses,
    their depth images untouched)."""
    from bench.lab.evaluation import MemoryMap
    from monoloc.core.registration import RunCorrection
    from monoloc.server.ingest.register import RegistrationTarget, correct_source, register_source
    from monoloc.server.ingest.sources import read_tum_run
    from monoloc.server.vision.vocabulary import load_default_vocabulary

    memory = MemoryMap.empty(load_default_vocabulary())
    memory.add_run(read_kitti_sequence(kitti_root.root))
    run = read_tum_run(tum_run)
    shift_world_m = np.array([0.15, -0.1])
    planted = RunCorrection(np.tile(shift_world_m, (len(run.frames), 1)), 0, 0, np.zeros(2))
    shifted = correct_source(run, planted)
    target = RegistrationTarget(memory.vocabulary, memory.index, memory.lookup)
    lenient = RegistrationConfig(min_frames=3)
    registered, correction = register_source(
        shifted, target, np.random.default_rng(0), config=lenient
    )
    assert correction.used >= 3 and type(registered) is type(run)
    for before, after in zip(run.frames, registered.frames, strict=True):
        assert after.depth_path == before.depth_path  # only the pose changed
        error = np.linalg.norm(after.T_world_from_cam[:2, 3] - before.T_world_from_cam[:2, 3])
        assert error < 0.03, error


def test_the_registration_line_says_whether_the_run_moved():
    from monoloc.server.ingest.report import registration_text

    moved = {
        "frames_measured": 33,
        "frames_used": 27,
        "offset_mean_m": [0.0551, 0.008],
        "offset_max_m": 0.0588,
        "noise_m": [0.07, 0.09],
    }
    assert registration_text(moved) == (
        "27 of 33 localized frames used; moved by x +0.055 m, y +0.008 m on average "
        "(at most 0.059 m)"
    )
    still = {**moved, "frames_used": 12, "offset_mean_m": [0.0, 0.0], "offset_max_m": 0.0}
    assert registration_text(still) == "12 of 33 localized frames used; not moved"

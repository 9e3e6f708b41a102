"""The vehicle end to end: a tiny sim run replayed against a live server over the
WebSocket stream with the particle filter (issue 6's acceptance test), the `monoloc
drive` command, and real-time replay with a server that falls behind."""

from __future__ import annotations

import time

import numpy as np
import pytest
from e2e_helpers import QUERY_SEQ, printed_rmse_m, query_drive_args, run_monoloc

from monoloc.client.api import MonolocClient
from monoloc.client.drive import DriveConfig, drive
from monoloc.client.particle_filter import FilterConfig
from monoloc.client.replay import read_run
from monoloc.client.trajectory import poses_from_planar
from monoloc.core.geometry import zup_to_kitti


def test_replay_of_a_tiny_sim_run_ends_within_half_a_metre(live_map):
    run = read_run(live_map.dataset, QUERY_SEQ)
    assert run.lever_arm_m == pytest.approx(1.0)  # the sim rig: camera 1 m ahead of the axle
    with MonolocClient(live_map.url, live_map.keys.localize) as client:
        map_id = client.find_map_id(live_map.map_name)
        model, calibrated = client.measurement_model(map_id)
        result = drive(client, map_id, run, model, DriveConfig())
        # the run's camera was registered once; asking again finds it, registers nothing
        same = [c for c in client.cameras() if c[2] == run.intrinsics]
        assert len(same) == 1
        assert client.camera_id(run.intrinsics) == same[0][0]
        assert [c[2] for c in client.cameras()].count(run.intrinsics) == 1
    m = result.metrics
    assert not calibrated
    assert m.coverage >= 0.8, m
    assert m.position_rmse_m < 0.5, m
    assert m.heading_rmse_deg < 2.0, m
    assert not result.dropped.any() and not result.errors  # as fast as possible: no drops
    # With the sim's recording errors of issue 13.4 (exposure and gray-level changes
    # between runs, calibration, LiDAR sync), query frames ~22-35 of this tiny run fall
    # below min_inliers; the filter carries them (coverage above).
    assert np.mean(result.n_hypotheses > 0) >= 0.6
    answered = [t for t, n in zip(result.server_timings_ms, result.n_hypotheses, strict=True) if n]
    assert all(t["total"] > 0 for t in answered)


def test_monoloc_drive_writes_trajectories_and_prints_the_metrics(live_map, tmp_path):
    out = tmp_path / "traj" / "query"
    done = run_monoloc("drive", *query_drive_args(live_map, out))
    assert done.returncode == 0, done.stderr
    for label in ("position RMSE", "position median", "heading RMSE", "within 0.25 m / 2 deg"):
        assert label in done.stdout, done.stdout
    assert printed_rmse_m(done.stdout) < 0.5
    assert "frames 10..29 of 40 selected (20 frames)" in done.stderr
    assert "map not calibrated" in done.stderr and "dataset.json" in done.stderr
    tum = np.loadtxt(out.with_name("query.tum.txt"))
    kitti = np.loadtxt(out.with_name("query.kitti.txt"))
    assert tum.shape[1] == 8 and kitti.shape[1] == 12 and len(tum) == len(kitti) >= 16
    run = read_run(live_map.dataset, QUERY_SEQ).select(slice(10, 30))
    frames = np.searchsorted(run.timestamps_s, tum[:, 0] - 1e-4)
    np.testing.assert_allclose(tum[:, 0], run.timestamps_s[frames], atol=1e-6)
    assert np.all(np.abs(np.linalg.norm(tum[:, 4:], axis=1) - 1) < 1e-6)  # unit quaternions
    # The KITTI file is in the dataset's own convention: compare with poses/01.txt.
    truth_kitti = np.loadtxt(live_map.dataset / "poses" / f"{QUERY_SEQ}.txt")[10:30][frames]
    ground_error = np.hypot(*(kitti[:, [3, 11]] - truth_kitti[:, [3, 11]]).T)
    assert np.median(ground_error) < 0.5
    expected = zup_to_kitti(poses_from_planar(run.truth_world[frames]))
    rot_error = np.abs(kitti.reshape(-1, 3, 4)[:, :, :3] - expected[:, :3, :3]).max()
    assert rot_error < 0.1


def test_monoloc_drive_names_an_unknown_map_in_one_line(live_map):
    done = run_monoloc(
        "drive",
        str(live_map.dataset / "sequences" / QUERY_SEQ),
        "--server",
        live_map.url,
        "--map",
        "nowhere",
        "--key",
        live_map.keys.localize,
    )
    assert done.returncode == 1
    assert done.stderr.strip().splitlines()[-1].startswith("error: no map named 'nowhere'")


def test_realtime_replay_paces_frames_and_predicts_through_dropped_ones(live_map, monkeypatch):
    n = 16
    run = read_run(live_map.dataset, QUERY_SEQ).select(slice(0, n))
    registry = live_map.app.state.monoloc.registry
    original = registry.localize

    def behind(*args, **kwargs):  # a server that needs 0.25 s per 0.1 s frame
        time.sleep(0.25)
        return original(*args, **kwargs)

    monkeypatch.setattr(registry, "localize", behind)
    config = DriveConfig(filter=FilterConfig(n_particles=500), realtime=True)
    with MonolocClient(live_map.url, live_map.keys.localize) as client:
        model, _ = client.measurement_model(live_map.map_id)
        result = drive(client, live_map.map_id, run, model, config)
    processed = ~result.dropped & ~np.isin(np.arange(n), list(result.errors))
    # every frame answered once, in order: processed or dropped, nothing lost
    assert np.all(np.isfinite(result.latency_ms))
    assert processed.sum() + result.dropped.sum() == n and not result.errors
    assert result.dropped.sum() >= 5, result.dropped
    assert processed[0] and processed[-1]  # the first finds an empty queue; newest never stale
    assert np.all(result.n_hypotheses[result.dropped] == 0)
    assert np.all(result.latency_ms[processed] >= 250)
    # a dropped frame is a prediction step: the estimate still moves with the car
    assert np.all(np.isfinite(result.estimates_world))
    assert result.metrics.position_rmse_m < 0.5, result.metrics
    # paced by the recorded timestamps, not as fast as possible
    offsets = (result.sent_at_s - result.sent_at_s[0]) - (run.timestamps_s - run.timestamps_s[0])
    assert np.all(offsets > -0.005) and np.all(offsets < 0.15), offsets
    assert result.wall_s >= run.timestamps_s[-1] - run.timestamps_s[0]

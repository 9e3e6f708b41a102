"""The replay loop (monoloc.client.drive) against a scripted stream: the filter's prior goes out
with every frame once initialised (moved to the frame's time), dropped frames and frames
the server could not process become prediction-only steps and are accounted for, and an
answer out of order is refused. The same loop against a live server: tests/e2e."""

from __future__ import annotations

import dataclasses
import json
import math
import queue
import time
from pathlib import Path

import numpy as np
import pytest

from monoloc.client.api import ServerError
from monoloc.client.drive import DriveConfig, PriorConfig, drive
from monoloc.client.particle_filter import FilterConfig
from monoloc.client.replay import ReplayRun
from monoloc.client.report import summary_rows
from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.core.measurement import MeasurementModel

SPEED_MPS = 5.0
CAMERA = CameraIntrinsics(640.0, 640.0, 511.5, 287.5, 1024, 576)  # a fleet camera


def _run(tmp_path: Path, n: int = 20, dt: float = 0.1) -> ReplayRun:
    """Straight along +X at 5 m/s; the frames are placeholder files."""
    t = np.arange(n) * dt
    truth = np.stack([SPEED_MPS * t, np.full(n, 2.0), np.zeros(n)], axis=1)
    paths = []
    for i in range(n):
        path = tmp_path / f"{i:06d}.png"
        path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes([i]))
        paths.append(path)
    signals = np.tile([SPEED_MPS, 0.0], (n, 1))
    return ReplayRun("synthetic", paths, t, signals, truth, ["a note"], intrinsics=CAMERA)


class FakeStream:
    """Answers each frame in order: hypotheses near the truth, or dropped / error."""

    def __init__(self, truth, dropped=(), errors=(), swap=None, rng_seed=0):
        self.truth, self.dropped, self.errors, self.swap = truth, set(dropped), set(errors), swap
        self.rng = np.random.default_rng(rng_seed)
        self.sent: list[dict] = []
        self.pending: queue.Queue = queue.Queue()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None

    def send(
        self, seq, t_s, image_bytes, prior=None, k=None, seed=None, intrinsics=None, camera_id=None
    ):
        self.sent.append(
            {
                "seq": seq,
                "t": t_s,
                "prior": prior,
                "k": k,
                "intrinsics": intrinsics,
                "camera_id": camera_id,
                "at": time.perf_counter(),
            }
        )
        self.pending.put(seq)

    def _answer(self, seq):
        if seq in self.dropped:
            return {"seq": seq, "dropped": True, "reason": "stale"}
        if seq in self.errors:
            return {"seq": seq, "error": {"code": "invalid_input", "message": "bad frame"}}
        x, y, yaw = self.truth[seq] + self.rng.normal(0, [0.05, 0.05, 0.005])
        hyp = {
            "pose": {"x_m": x, "y_m": y, "yaw_rad": yaw},
            "entry_pose": {"x_m": x - 1.0, "y_m": y, "yaw_rad": yaw},
            "e_vlad": 0.9,
            "n_inliers": 50,
        }
        return {"seq": seq, "hypotheses": [hyp], "map_version": 1, "timings_ms": {"total": 9.0}}

    def receive(self):
        seq = self.pending.get(timeout=10)
        if self.swap is not None and seq == self.swap:
            seq += 1
        return json.loads(json.dumps(self._answer(seq)))


class FakeClient:
    """The stream's client, with a camera registry: ``registered`` lists the cameras."""

    def __init__(self, stream):
        self._stream = stream
        self.registered: list = []

    def camera_id(self, intrinsics, name=None):
        if intrinsics not in self.registered:
            self.registered.append(intrinsics)
        return 100 + self.registered.index(intrinsics)

    def stream(self, map_id, timeout_s=30.0):
        return self._stream

    def geo_reference(self, map_id):
        return None  # a map without a geographic reference


# The fake server answers one hypothesis per frame; these tests are about the drive loop,
# so the filter starts on the first frame with a hypothesis (init_min_agreeing=1).
FILTER = FilterConfig(n_particles=300, init_min_agreeing=1)
CONFIG = DriveConfig(filter=FILTER)


def test_prior_follows_the_filter_and_misses_become_prediction_steps(tmp_path):
    run = _run(tmp_path)
    stream = FakeStream(run.truth_world, dropped={5, 6}, errors={9})
    result = drive(FakeClient(stream), 1, run, MeasurementModel(), CONFIG)
    assert [s["seq"] for s in stream.sent] == list(range(len(run)))
    assert stream.sent[0]["prior"] is None  # nothing known yet: global search
    for sent in stream.sent[1:]:
        prior, truth = sent["prior"], run.truth_world[sent["seq"]]
        # moved to this frame's time: within the hypotheses' noise of the truth
        assert math.hypot(prior.x_m - truth[0], prior.y_m - truth[1]) < 0.3, sent
        assert PriorConfig().min_radius_m <= prior.radius_m <= PriorConfig().max_radius_m
        assert abs(prior.yaw_rad - truth[2]) < 0.05
    assert np.flatnonzero(result.dropped).tolist() == [5, 6]
    assert list(result.errors) == [9] and "invalid_input: bad frame" in result.errors[9]
    assert result.n_hypotheses[[5, 6, 9]].tolist() == [0, 0, 0]
    assert np.all(result.n_hypotheses[[0, 1, 2, 7, 8, 10]] == 1)
    assert np.all(np.isfinite(result.estimates_world))  # predicted through the misses
    assert result.metrics.position_rmse_m < 0.15 and result.metrics.coverage == 1.0
    assert np.all(np.isfinite(result.latency_ms)) and np.all(np.diff(result.sent_at_s) >= 0)
    assert result.notes[0] == "a note" and "1 frame(s) with an error" in result.notes[1]
    rows = dict(summary_rows(result))
    assert rows["dropped by the server"] == "2" and rows["server errors"] == "1"
    assert rows["frames"] == "20" and rows["position RMSE"].endswith(" m")


def test_without_prior_every_frame_is_a_global_search(tmp_path):
    run = _run(tmp_path, n=6)
    stream = FakeStream(run.truth_world)
    drive(FakeClient(stream), 1, run, MeasurementModel(), DriveConfig(use_prior=False, k=3))
    assert all(s["prior"] is None and s["k"] == 3 for s in stream.sent)


def test_an_answer_out_of_order_is_refused(tmp_path):
    run = _run(tmp_path, n=6)
    with pytest.raises(ServerError, match="answered frame 4 when frame 3 was due"):
        drive(FakeClient(FakeStream(run.truth_world, swap=3)), 1, run, MeasurementModel(), CONFIG)


def test_realtime_sends_at_the_recorded_times(tmp_path):
    run = _run(tmp_path, n=12, dt=0.04)
    stream = FakeStream(run.truth_world)
    config = DriveConfig(filter=FILTER, realtime=True)
    result = drive(FakeClient(stream), 1, run, MeasurementModel(), config)
    sent = np.array([s["at"] for s in stream.sent])
    offsets = (sent - sent[0]) - (run.timestamps_s - run.timestamps_s[0])
    # never early (as fast as possible would be ~0.4 s early by the end); late only by
    # scheduling noise
    assert np.all(offsets > -0.002) and np.all(offsets < 0.08), offsets
    assert result.wall_s >= run.timestamps_s[-1] - run.timestamps_s[0]
    assert np.all(np.isfinite(result.estimates_world))


def test_an_empty_selection_is_refused(tmp_path):
    run = _run(tmp_path, n=4).select(slice(4, None))
    with pytest.raises(InvalidInputError, match="no frames to replay"):
        drive(FakeClient(FakeStream(np.zeros((0, 3)))), 1, run, MeasurementModel(), CONFIG)


def test_the_run_s_own_camera_goes_with_every_frame_in_both_modes(tmp_path):
    run = _run(tmp_path, n=6)
    for realtime in (False, True):
        stream = FakeStream(run.truth_world)
        client = FakeClient(stream)
        drive(client, 1, run, MeasurementModel(), DriveConfig(realtime=realtime))
        # registered once, then named by its id in every frame
        assert client.registered == [CAMERA]
        assert [s["camera_id"] for s in stream.sent] == [100] * 6


def test_a_run_whose_camera_is_unknown_stops_before_the_first_frame(tmp_path):
    run = dataclasses.replace(_run(tmp_path, n=4), intrinsics=None)
    stream = FakeStream(run.truth_world)
    client = FakeClient(stream)
    with pytest.raises(InvalidInputError, match="camera that took the frames is unknown"):
        drive(client, 1, run, MeasurementModel(), CONFIG)
    assert stream.sent == [] and client.registered == []


def test_a_drive_whose_every_frame_was_refused_says_so(tmp_path):
    run = _run(tmp_path, n=5)
    everything = drive(
        FakeClient(FakeStream(run.truth_world, errors=range(5))), 1, run, MeasurementModel()
    )
    assert everything.all_refused and len(everything.errors) == 5
    some = drive(FakeClient(FakeStream(run.truth_world, errors={2})), 1, run, MeasurementModel())
    assert not some.all_refused

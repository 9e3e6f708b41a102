"""The vehicle's loop (monoloc.client.tracking) driven by a fake Localizer with known
hypotheses: the prior handed to the localizer is the filter's estimate moved to the
frame's time, frames without hypotheses are prediction-only steps, and the loop is
ParticleFilter.step fed frame by frame. The remote localizers' answers: tests below."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import httpx
import numpy as np
import pytest

from monoloc.client.api import LocalizeAnswer, MonolocClient, ServerError
from monoloc.client.localizer import HttpLocalizer, StreamLocalizer
from monoloc.client.particle_filter import FilterConfig, ParticleFilter
from monoloc.client.tracking import PriorConfig, Tracker, track
from monoloc.core.errors import InvalidInputError
from monoloc.core.measurement import Hypotheses, MeasurementModel
from monoloc.core.prior import RetrievalPrior

DT_S, SPEED_MPS, YAW_RATE_RADPS = 0.1, 6.0, 0.05
CONFIG = FilterConfig(n_particles=300)


def _truth(n: int) -> np.ndarray:
    """A gentle left turn: poses (n, 3) driven with the signals of _signals."""
    poses = [np.array([10.0, -4.0, 0.3])]
    for _ in range(n - 1):
        x, y, yaw = poses[-1]
        poses.append(
            np.array(
                [
                    x + SPEED_MPS * math.cos(yaw) * DT_S,
                    y + SPEED_MPS * math.sin(yaw) * DT_S,
                    yaw + YAW_RATE_RADPS * DT_S,
                ]
            )
        )
    return np.array(poses)


def _signals(n: int) -> tuple[np.ndarray, np.ndarray]:
    return np.arange(n) * DT_S, np.tile([SPEED_MPS, YAW_RATE_RADPS], (n, 1))


class FakeLocalizer:
    """Three hypotheses near the truth of each frame, none for the ``missing`` frames;
    records the prior and k of every call. Images are the frame numbers."""

    def __init__(self, truth: np.ndarray, missing=(), seed: int = 0) -> None:
        self.truth, self.missing = truth, set(missing)
        self.rng = np.random.default_rng(seed)
        self.calls: list[tuple[int, RetrievalPrior | None, int | None]] = []

    def hypotheses(self, i: int) -> Hypotheses:
        if i in self.missing:
            return Hypotheses.empty()
        poses = self.truth[i] + self.rng.normal(0, [0.05, 0.05, 0.005], size=(3, 3))
        return Hypotheses(poses, poses - [1.0, 0.0, 0.0], np.full(3, 0.9))

    def localize(self, image, prior=None, k=None) -> LocalizeAnswer:
        self.calls.append((image, prior, k))
        return LocalizeAnswer(self.hypotheses(image), None, {"total": 1.0}, {})


def _tracker(n: int, seed: int = 7, config: FilterConfig = CONFIG, **kwargs) -> Tracker:
    times, signals = _signals(n)
    rng = np.random.default_rng(seed)
    return Tracker(config, MeasurementModel(), rng, times, signals, **kwargs)


def test_the_prior_is_the_last_estimate_moved_to_the_frame_time():
    n = 15
    truth = _truth(n)
    localizer = FakeLocalizer(truth)
    tracker = _tracker(n)
    estimates = track(tracker, localizer, range(n), k=4)
    assert [call[0] for call in localizer.calls] == list(range(n))
    assert all(call[2] == 4 for call in localizer.calls)
    assert localizer.calls[0][1] is None  # nothing known yet: a global search
    # moved as the particles are (client/motion.py): the exact arc of the step, the
    # camera at the reference point (no mounting in CONFIG)
    turn = YAW_RATE_RADPS * DT_S
    chord = SPEED_MPS * DT_S * math.sin(turn / 2) / (turn / 2)
    for i in range(1, n):
        prior, (x, y, yaw) = localizer.calls[i][1], estimates[i - 1]
        assert prior.x_m == pytest.approx(x + chord * math.cos(yaw + turn / 2), abs=1e-12)
        assert prior.y_m == pytest.approx(y + chord * math.sin(yaw + turn / 2), abs=1e-12)
        assert prior.yaw_rad == pytest.approx(yaw + turn, abs=1e-12)
        assert PriorConfig().min_radius_m <= prior.radius_m <= PriorConfig().max_radius_m
    assert np.abs(estimates - truth)[:, :2].max() < 0.2


def test_the_loop_is_the_filter_stepped_frame_by_frame():
    n = 20
    truth = _truth(n)
    missing = {0, 1, 7, 8, 9, 15}  # before initialisation, and in the middle
    # the particles alone (the refinement of the reported pose: tests/client/test_refine.py)
    config = replace(CONFIG, refine=None)
    tracker = _tracker(n, config=config)
    estimates = track(tracker, FakeLocalizer(truth, missing), range(n))
    # By hand, with the same seeds: predict with the previous frame's signals, then
    # initialise or update; frames without hypotheses only predict.
    pf = ParticleFilter(config, MeasurementModel(), np.random.default_rng(7))
    fake = FakeLocalizer(truth, missing)
    times, signals = _signals(n)
    expected = np.full((n, 3), np.nan)
    for i in range(n):
        if i > 0:
            pf.predict(float(times[i] - times[i - 1]), *signals[i - 1])
        hyps = fake.hypotheses(i)
        if not pf.initialised:
            if len(hyps):
                pf.initialise_from_hypotheses(hyps)
        else:
            pf.update(hyps)
        if pf.initialised:
            expected[i] = pf.estimate().pose_world
    assert np.isnan(estimates[:2]).all() and np.isfinite(estimates[2:]).all()
    np.testing.assert_array_equal(estimates, expected)
    # the missing frames moved with the car
    assert np.abs(estimates[7:10] - truth[7:10])[:, :2].max() < 0.3


def test_without_hypotheses_every_frame_is_a_prediction_step():
    n = 12
    truth = _truth(n)
    localizer = FakeLocalizer(truth, missing=range(3, n))
    tracker = _tracker(n)
    estimates = track(tracker, localizer, range(n))
    moved = np.linalg.norm(np.diff(estimates[2:, :2], axis=0), axis=1)
    # speed noise of the motion model aside, each step moves by speed * dt
    np.testing.assert_allclose(moved, SPEED_MPS * DT_S, rtol=0.1)
    assert all(call[1] is not None for call in localizer.calls[1:])


def test_no_prior_when_asked_for_none():
    n = 8
    localizer = FakeLocalizer(_truth(n))
    track(_tracker(n, use_prior=False), localizer, range(n))
    assert all(call[1] is None for call in localizer.calls)


def test_the_prior_widens_then_gives_way_to_the_whole_map_without_support():
    n = 24
    localizer = FakeLocalizer(_truth(n), missing=range(5, n))
    track(_tracker(n), localizer, range(n))
    config = PriorConfig()
    priors = [call[1] for call in localizer.calls]
    # frame i's prior follows i - 5 frames without hypotheses
    for i in range(6, 6 + config.widen_after_frames):
        assert priors[i].radius_m < 1.1 * config.min_radius_m
    radii = [p.radius_m for p in priors[6 : 6 + config.global_after_frames]]
    assert all(
        b / a == pytest.approx(config.widen_factor, rel=0.05)
        for a, b in zip(radii[2:-1], radii[3:], strict=True)
    )
    assert radii[-1] > 10 * config.min_radius_m
    assert all(p is None for p in priors[6 + config.global_after_frames :])


def test_hypotheses_far_away_that_move_with_the_car_reseed_the_filter():
    n = 14
    truth = _truth(n)
    far = truth.copy()
    far[5:, 0] += 200.0  # kidnapped at frame 5
    localizer = FakeLocalizer(far)
    tracker = _tracker(n)
    track(tracker, localizer, range(n))
    priors = [call[1] for call in localizer.calls]
    # frames 5, 6, 7 disagree with the particles: the prior stays, then starts to widen;
    # frames 0-4 supported the track, so the new place needs six consistent frames:
    # frame 10 re-seeds (not frame 9), and frame 11's prior is there
    assert priors[7].radius_m < priors[8].radius_m
    assert tracker.filter.n_reseeds == 1
    assert priors[10].x_m < 150.0
    assert priors[11].x_m > 150.0 and priors[11].radius_m < 1.1 * PriorConfig().min_radius_m
    assert np.abs(tracker.estimates_world[10:] - far[10:])[:, :2].max() < 0.3


def test_frames_are_stepped_in_order():
    tracker = _tracker(5)
    tracker.step(0, Hypotheses.empty())
    with pytest.raises(InvalidInputError, match="frame 2 stepped after frame 0"):
        tracker.step(2, Hypotheses.empty())


class ScriptedStream:
    """Answers the frames sent with ``answers[seq]`` (a dict, ``seq`` added)."""

    def __init__(self, answers: dict[int, dict], swap: bool = False) -> None:
        self.answers, self.swap = answers, swap
        self.sent: list[tuple] = []

    def send(
        self, seq, t_s, image_bytes, prior=None, k=None, seed=None, intrinsics=None, camera_id=None
    ):
        self.sent.append((seq, t_s, prior, k))

    def receive(self) -> dict:
        seq = self.sent[-1][0] + (1 if self.swap else 0)
        return json.loads(json.dumps({**self.answers.get(seq, {}), "seq": seq}))


HYP = {
    "pose": {"x_m": 1.0, "y_m": 2.0, "yaw_rad": 0.1},
    "entry_pose": {"x_m": 0.0, "y_m": 2.0, "yaw_rad": 0.1},
    "e_vlad": 0.8,
    "n_inliers": 40,
}


def test_the_stream_localizer_answers_one_frame_at_a_time():
    stream = ScriptedStream(
        {
            0: {"hypotheses": [HYP], "timings_ms": {"total": 5.0}, "map_version": 3},
            1: {"dropped": True, "reason": "stale"},
            2: {"error": {"code": "invalid_input", "message": "bad frame"}},
        }
    )
    localizer = StreamLocalizer(stream, timestamps_s=[0.5, 0.6, 0.7])
    prior = RetrievalPrior(1.0, 2.0, 10.0)
    answers = [localizer.localize(b"png", prior if i else None, 5) for i in range(3)]
    assert stream.sent == [(0, 0.5, None, 5), (1, 0.6, prior, 5), (2, 0.7, prior, 5)]
    ok, dropped, failed = answers
    assert len(ok.hypotheses) == 1 and ok.map_version == 3 and ok.timings_ms == {"total": 5.0}
    np.testing.assert_array_equal(ok.best_pose_world, [1.0, 2.0, 0.1])
    assert dropped.dropped and len(dropped.hypotheses) == 0 and dropped.error is None
    assert failed.error == "invalid_input: bad frame" and len(failed.hypotheses) == 0
    assert np.isnan(failed.best_pose_world).all()


def test_the_stream_localizer_refuses_an_answer_out_of_order():
    localizer = StreamLocalizer(ScriptedStream({}, swap=True))
    with pytest.raises(ServerError, match="answered frame 1 when frame 0 was due"):
        localizer.localize(b"png")


def test_the_http_localizer_posts_the_frame_with_its_prior():
    seen = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append((request.url.path, request.content))
        return httpx.Response(200, json={"hypotheses": [HYP], "map_version": 1})

    client = MonolocClient("http://fake", "mlk_test", transport=httpx.MockTransport(handler))
    with client:
        prior = RetrievalPrior(4.0, 5.0, 12.0)
        answer = HttpLocalizer(client, 7).localize(b"\x89PNG", prior, 3)
    assert seen[0][0] == "/v1/maps/7/localize"
    assert b'name="prior_radius_m"' in seen[0][1] and b'name="k"' in seen[0][1]
    assert len(answer.hypotheses) == 1
